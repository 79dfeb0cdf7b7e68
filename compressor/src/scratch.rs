//! An unnamed temporary file that records are appended to and read back from by offset: where
//! a compression keeps what it made but need not hold in memory (a trial's coded bricks, the
//! kept tops beyond their memory budget). The file has no name, so it is gone when the last
//! handle is dropped, whether the run ends, fails or is killed. `tempfile` gives the file; the
//! append-and-read-back by offset from many threads under one lock is this module's.

use std::io::{Read, Seek, SeekFrom, Write};

/// An unnamed temporary file shared by threads, appended to and read back by offset.
#[derive(Debug)]
pub struct ScratchFile {
    /// The file and the length written so far.
    file: std::sync::Mutex<(std::fs::File, u64)>,
}

impl ScratchFile {
    /// An empty file in `dir` (`None`: the temporary directory).
    pub fn new(dir: Option<&std::path::Path>) -> std::io::Result<ScratchFile> {
        let file = match dir {
            Some(d) => tempfile::tempfile_in(d),
            None => tempfile::tempfile(),
        }?;
        Ok(ScratchFile {
            file: std::sync::Mutex::new((file, 0)),
        })
    }

    /// Appends `bytes`; the offset they start at.
    pub fn append(&self, bytes: &[u8]) -> std::io::Result<u64> {
        let mut g = self.file.lock().unwrap_or_else(|p| p.into_inner());
        let offset = g.1;
        // From the end as recorded, wherever a read or a failed write left the file's cursor.
        g.0.seek(SeekFrom::Start(offset))?;
        g.0.write_all(bytes)?;
        g.1 += bytes.len() as u64;
        Ok(offset)
    }

    /// Gives the disk space of the `len` bytes appended at `offset` back to the file system
    /// (a hole punched in the file; its length and other records stay). Reading them after
    /// gives zeros. An error where the file system cannot punch holes: nothing was freed.
    pub fn release(&self, offset: u64, len: u64) -> std::io::Result<()> {
        let g = self.file.lock().unwrap_or_else(|p| p.into_inner());
        if offset.checked_add(len).is_none_or(|end| end > g.1) {
            return Err(std::io::Error::other(format!(
                "{len} bytes at {offset} released of a temporary file of {}",
                g.1
            )));
        }
        #[cfg(target_os = "linux")]
        {
            use rustix::fs::{fallocate, FallocateFlags};
            let flags = FallocateFlags::PUNCH_HOLE | FallocateFlags::KEEP_SIZE;
            fallocate(&g.0, flags, offset, len).map_err(std::io::Error::from)
        }
        #[cfg(not(target_os = "linux"))]
        Err(std::io::Error::new(
            std::io::ErrorKind::Unsupported,
            "holes are punched in temporary files on Linux only",
        ))
    }

    /// Bytes appended so far.
    pub fn len(&self) -> u64 {
        self.file.lock().unwrap_or_else(|p| p.into_inner()).1
    }

    /// Whether nothing was appended.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The `len` bytes appended at `offset`.
    pub fn read(&self, offset: u64, len: usize) -> std::io::Result<Vec<u8>> {
        let mut bytes = Vec::new();
        self.copy_to(offset, len as u64, &mut bytes)?;
        Ok(bytes)
    }

    /// Copies the `len` bytes appended at `offset` to `out`.
    pub fn copy_to(
        &self,
        offset: u64,
        len: u64,
        out: &mut dyn std::io::Write,
    ) -> std::io::Result<()> {
        let mut g = self.file.lock().unwrap_or_else(|p| p.into_inner());
        if offset.checked_add(len).is_none_or(|end| end > g.1) {
            return Err(std::io::Error::other(format!(
                "{len} bytes at {offset} asked of a temporary file of {}",
                g.1
            )));
        }
        g.0.seek(SeekFrom::Start(offset))?;
        let copied = std::io::copy(&mut (&mut g.0).take(len), out)?;
        if copied != len {
            return Err(std::io::Error::other(format!(
                "the temporary file holds {copied} of {len} bytes at {offset}"
            )));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Records appended from several threads read back whole from their offsets, and a read
    /// past what was written is refused.
    #[test]
    fn records_read_back_from_their_offsets() {
        let f = ScratchFile::new(None).unwrap();
        assert!(f.is_empty());
        let records: Vec<Vec<u8>> = (0..16u8).map(|i| vec![i; 1 + 37 * i as usize]).collect();
        let offsets: Vec<u64> = std::thread::scope(|s| {
            let handles: Vec<_> = records
                .iter()
                .map(|r| s.spawn(|| f.append(r).unwrap()))
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let total: usize = records.iter().map(Vec::len).sum();
        assert_eq!(f.len(), total as u64);
        for (r, &o) in records.iter().zip(&offsets) {
            assert_eq!(&f.read(o, r.len()).unwrap(), r);
            assert_eq!(f.read(o, r.len() / 2).unwrap(), r[..r.len() / 2]);
        }
        assert!(f.read(f.len() - 1, 2).is_err());
        assert!(f.read(u64::MAX, 1).is_err());
        assert_eq!(f.read(f.len(), 0).unwrap(), Vec::<u8>::new());
    }

    /// A record released gives its blocks back and reads as zeros; the records around it
    /// read as written, and a release past the end is refused.
    #[test]
    #[cfg(target_os = "linux")]
    fn a_released_record_gives_its_disk_space_back() {
        use std::os::unix::fs::MetadataExt;
        let f = ScratchFile::new(None).unwrap();
        let mib = 1 << 20;
        let offsets: Vec<u64> = (1..=3u8)
            .map(|i| f.append(&vec![i; mib]).unwrap())
            .collect();
        let blocks = || f.file.lock().unwrap().0.metadata().unwrap().blocks();
        let before = blocks();
        assert!(f.release(f.len(), 1).is_err());
        assert!(f.release(u64::MAX, 2).is_err());
        // Linux's file systems for temporary files (tmpfs, ext4, xfs, btrfs) punch holes.
        f.release(offsets[1], mib as u64).expect("a hole punched");
        // 512-byte blocks: the megabyte's 2048 of them, give or take the edges' blocks.
        assert!(blocks() + 1800 <= before, "{} of {before} blocks", blocks());
        assert!(f.read(offsets[1], mib).unwrap().iter().all(|b| *b == 0));
        assert_eq!(f.len(), 3 * mib as u64);
        assert_eq!(f.read(offsets[0], mib).unwrap(), vec![1; mib]);
        assert_eq!(f.read(offsets[2], mib).unwrap(), vec![3; mib]);
    }
}
