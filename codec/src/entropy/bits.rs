//! MSB-first bit I/O: one [`BitSink`] interface with an emitting sink ([`BitWriter`]) and a
//! counting sink ([`BitCounter`]), so that the size a rate estimator predicts by running the
//! real writing code against a counter is exactly the size written (rav1e's
//! `WriterCounter`/`WriterEncoder`), and a bounds-checked [`BitReader`].

use super::EntropyError;

/// Destination of an MSB-first bit stream.
pub trait BitSink {
    /// Appends the low `n` bits of `value`, most significant first. `n` must be at most 64; bits
    /// of `value` above the low `n` are ignored.
    fn put_bits(&mut self, value: u64, n: u32);

    /// Appends a single bit.
    fn put_bit(&mut self, bit: bool) {
        self.put_bits(bit as u64, 1);
    }

    /// Total number of bits appended so far.
    fn bits(&self) -> u64;
}

impl<S: BitSink + ?Sized> BitSink for &mut S {
    fn put_bits(&mut self, value: u64, n: u32) {
        (**self).put_bits(value, n)
    }

    fn put_bit(&mut self, bit: bool) {
        (**self).put_bit(bit)
    }

    fn bits(&self) -> u64 {
        (**self).bits()
    }
}

/// Mask of the low `n` bits (`n` ≤ 64).
#[inline]
pub(super) fn low_mask(n: u32) -> u64 {
    if n >= 64 {
        u64::MAX
    } else {
        (1u64 << n) - 1
    }
}

/// A [`BitSink`] that emits bytes into a `Vec<u8>`.
#[derive(Debug, Clone, Default)]
pub struct BitWriter {
    bytes: Vec<u8>,
    /// Pending bits, right-aligned; fewer than 8 between calls.
    acc: u64,
    acc_bits: u32,
}

impl BitWriter {
    /// An empty writer.
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty writer with room for `bytes` bytes.
    pub fn with_capacity(bytes: usize) -> Self {
        BitWriter {
            bytes: Vec::with_capacity(bytes),
            acc: 0,
            acc_bits: 0,
        }
    }

    /// Pads with zero bits up to the next byte boundary.
    pub fn align_to_byte(&mut self) {
        if self.acc_bits > 0 {
            self.put_bits(0, 8 - self.acc_bits);
        }
    }

    /// Finishes the stream: the last partial byte is padded with zero bits.
    pub fn finish(mut self) -> Vec<u8> {
        self.align_to_byte();
        self.bytes
    }

    #[inline]
    fn put_small(&mut self, value: u64, n: u32) {
        debug_assert!(n <= 32 && self.acc_bits < 8);
        self.acc = (self.acc << n) | (value & low_mask(n));
        self.acc_bits += n;
        while self.acc_bits >= 8 {
            self.acc_bits -= 8;
            self.bytes.push((self.acc >> self.acc_bits) as u8);
        }
        self.acc &= low_mask(self.acc_bits);
    }
}

impl BitSink for BitWriter {
    fn put_bits(&mut self, value: u64, n: u32) {
        debug_assert!(n <= 64, "put_bits: n = {n} > 64");
        let n = n.min(64);
        if n > 32 {
            self.put_small(value >> 32, n - 32);
            self.put_small(value, 32);
        } else if n > 0 {
            self.put_small(value, n);
        }
    }

    fn bits(&self) -> u64 {
        self.bytes.len() as u64 * 8 + self.acc_bits as u64
    }
}

/// A [`BitSink`] that only counts bits.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BitCounter {
    bits: u64,
}

impl BitCounter {
    /// A counter at zero.
    pub fn new() -> Self {
        Self::default()
    }

    /// The number of bytes [`BitWriter::finish`] would return for the same bits.
    pub fn bytes(&self) -> u64 {
        self.bits.div_ceil(8)
    }
}

impl BitSink for BitCounter {
    #[inline]
    fn put_bits(&mut self, _value: u64, n: u32) {
        debug_assert!(n <= 64, "put_bits: n = {n} > 64");
        self.bits += n.min(64) as u64;
    }

    fn bits(&self) -> u64 {
        self.bits
    }
}

/// Reads an MSB-first bit stream from a byte slice. Reads never go past the end: they return
/// [`EntropyError::UnexpectedEnd`] and leave the position unchanged.
#[derive(Debug, Clone)]
pub struct BitReader<'a> {
    data: &'a [u8],
    /// Bit position of the next bit to read.
    pos: u64,
}

impl<'a> BitReader<'a> {
    /// A reader positioned at the first bit of `data`.
    pub fn new(data: &'a [u8]) -> Self {
        BitReader { data, pos: 0 }
    }

    /// Number of bits consumed so far.
    pub fn position(&self) -> u64 {
        self.pos
    }

    /// Number of bits left in the input.
    pub fn bits_remaining(&self) -> u64 {
        (self.data.len() as u64 * 8).saturating_sub(self.pos)
    }

    /// Returns the next `n` bits (`n` is clamped to 64) without consuming them. Bits past the
    /// end of the input read as zero.
    #[inline]
    pub fn peek_bits(&self, n: u32) -> u64 {
        let n = n.min(64);
        if n == 0 {
            return 0;
        }
        let byte = (self.pos / 8) as usize;
        let offset = (self.pos % 8) as u32;
        // Fast path: the window lies in one 8-byte load.
        if n + offset <= 64 {
            if let Some(chunk) = self.data.get(byte..byte + 8) {
                let word = u64::from_be_bytes(chunk.try_into().expect("8 bytes")) << offset;
                return word >> (64 - n);
            }
        }
        let mut buf = [0u8; 16];
        match self.data.get(byte..byte + 16) {
            Some(chunk) => buf.copy_from_slice(chunk),
            None if byte < self.data.len() => {
                let end = self.data.len().min(byte + 9);
                buf[..end - byte].copy_from_slice(&self.data[byte..end]);
            }
            None => {}
        }
        let window = u128::from_be_bytes(buf) << offset;
        (window >> (128 - n)) as u64
    }

    /// Reads `n` bits (`n` ≤ 64) as an unsigned integer, first bit most significant.
    pub fn get_bits(&mut self, n: u32) -> Result<u64, EntropyError> {
        if n > 64 {
            return Err(EntropyError::out_of_range("bit count", n, 0, 64));
        }
        let value = self.peek_bits(n);
        self.consume(n)?;
        Ok(value)
    }

    /// Reads one bit.
    pub fn get_bit(&mut self) -> Result<bool, EntropyError> {
        Ok(self.get_bits(1)? != 0)
    }

    /// Skips `n` bits.
    pub fn consume(&mut self, n: u32) -> Result<(), EntropyError> {
        let remaining = self.bits_remaining();
        if n as u64 > remaining {
            return Err(EntropyError::UnexpectedEnd {
                needed: n as u64,
                remaining,
            });
        }
        self.pos += n as u64;
        Ok(())
    }

    /// Skips to the next byte boundary (no-op when already aligned).
    pub fn align_to_byte(&mut self) {
        let aligned = self.pos.div_ceil(8) * 8;
        self.pos = aligned.min(self.data.len() as u64 * 8).max(self.pos);
    }
}

/// Reads an MSB-first bit stream through a 64-bit buffer refilled eight bytes at a time, for
/// hot decoding loops: no bounds check per read, at the price of the caller refilling before
/// it peeks. Bits past the end read as zero; [`WordReader::overrun`] tells whether any were
/// consumed, which decoders check to stop on truncated or hostile input.
#[derive(Debug, Clone)]
pub struct WordReader<'a> {
    data: &'a [u8],
    /// Next byte to load (may pass the end: those bytes read as zero).
    next: usize,
    /// Buffered bits, the next one most significant; the bits after the valid ones are zero
    /// or the stream's own next bits.
    buf: u64,
    /// Valid bits in `buf`.
    bits: u32,
}

impl<'a> WordReader<'a> {
    /// Most bits [`WordReader::peek`] holds after a refill.
    pub const PEEK_BITS: u32 = 57;

    /// A reader positioned at the first bit of `data`.
    pub fn new(data: &'a [u8]) -> Self {
        let mut r = WordReader {
            data,
            next: 0,
            buf: 0,
            bits: 0,
        };
        r.refill();
        r
    }

    /// Tops the buffer up to at least [`WordReader::PEEK_BITS`] valid bits.
    #[inline(always)]
    pub fn refill(&mut self) {
        // No branch on whether the buffer needs bits (as unpredictable as the bits the symbols
        // took): a full buffer loads the next word too and takes no byte of it.
        if let Some(chunk) = self.data.get(self.next..self.next + 8) {
            let word = u64::from_be_bytes(chunk.try_into().expect("8 bytes"));
            // The loaded bits past the whole bytes taken are the stream's own next bits, so
            // OR-ing them in again on the next refill changes nothing.
            self.buf |= word.checked_shr(self.bits).unwrap_or(0);
            let bytes = (64 - self.bits) / 8;
            self.next += bytes as usize;
            self.bits += 8 * bytes;
        } else {
            self.refill_at_end();
        }
    }

    #[cold]
    fn refill_at_end(&mut self) {
        while self.bits < Self::PEEK_BITS {
            let byte = self.data.get(self.next).copied().unwrap_or(0);
            self.buf |= (byte as u64) << (56 - self.bits);
            self.next += 1;
            self.bits += 8;
        }
    }

    /// The buffered bits, the next one most significant (valid: at least
    /// [`WordReader::PEEK_BITS`] after a refill).
    #[inline(always)]
    pub fn peek(&self) -> u64 {
        self.buf
    }

    /// Skips `n` ≤ [`WordReader::PEEK_BITS`] bits of a refilled buffer.
    #[inline(always)]
    pub fn consume(&mut self, n: u32) {
        debug_assert!(n <= self.bits && n < 64);
        self.buf <<= n;
        self.bits -= n;
    }

    /// Reads `n` ≤ [`WordReader::PEEK_BITS`] bits of a refilled buffer as an unsigned
    /// integer, first bit most significant, without a branch on `n` (0 reads nothing): for
    /// counts as unpredictable as the data.
    #[inline(always)]
    pub fn take_refilled(&mut self, n: u32) -> u64 {
        debug_assert!(n <= Self::PEEK_BITS);
        // Two shifts, so that n = 0 shifts by 64 in all without overflowing one.
        let v = (self.buf >> (63 - n)) >> 1;
        self.consume(n);
        v
    }

    /// Reads `n` ≤ [`WordReader::PEEK_BITS`] bits as an unsigned integer, first bit most
    /// significant.
    #[inline(always)]
    pub fn get_bits(&mut self, n: u32) -> u64 {
        debug_assert!(n <= Self::PEEK_BITS);
        if n == 0 {
            return 0;
        }
        self.refill();
        let v = self.buf >> (64 - n);
        self.consume(n);
        v
    }

    /// Number of bits consumed so far (past the end too).
    pub fn position(&self) -> u64 {
        self.next as u64 * 8 - self.bits as u64
    }

    /// Whether bits past the end of the data were consumed.
    pub fn overrun(&self) -> bool {
        self.position() > self.data.len() as u64 * 8
    }

    /// Bits left before the end of the data (0 once past it).
    pub fn bits_remaining(&self) -> u64 {
        (self.data.len() as u64 * 8).saturating_sub(self.position())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn writes_msb_first_and_pads_with_zeros() {
        let mut w = BitWriter::new();
        w.put_bit(true);
        w.put_bits(0b01, 2);
        w.put_bits(0xABC, 12);
        assert_eq!(w.bits(), 15);
        assert_eq!(w.finish(), vec![0b1011_0101, 0b0111_1000]);
    }

    #[test]
    fn full_64_bit_values_round_trip() {
        let mut w = BitWriter::new();
        w.put_bit(true);
        w.put_bits(u64::MAX - 5, 64);
        w.put_bits(0x8000_0000_0000_0001, 64);
        let bytes = w.finish();
        let mut r = BitReader::new(&bytes);
        assert!(r.get_bit().unwrap());
        assert_eq!(r.get_bits(64).unwrap(), u64::MAX - 5);
        assert_eq!(r.get_bits(64).unwrap(), 0x8000_0000_0000_0001);
        assert_eq!(r.bits_remaining(), 7);
    }

    #[test]
    fn reader_reports_end_without_moving() {
        let data = [0xFFu8, 0x01];
        let mut r = BitReader::new(&data);
        assert_eq!(r.get_bits(12).unwrap(), 0xFF0);
        assert_eq!(
            r.get_bits(5),
            Err(EntropyError::UnexpectedEnd {
                needed: 5,
                remaining: 4
            })
        );
        assert_eq!(r.position(), 12);
        assert_eq!(r.peek_bits(64), 1u64 << 60);
        assert_eq!(r.get_bits(4).unwrap(), 1);
        assert_eq!(r.peek_bits(64), 0);
        assert!(r.get_bit().is_err());
        assert!(r.get_bits(65).is_err());
        assert!(r.consume(1).is_err());
        r.align_to_byte();
        assert_eq!(r.position(), 16);
    }

    #[test]
    fn empty_reader() {
        let r = BitReader::new(&[]);
        assert_eq!(r.peek_bits(64), 0);
        assert_eq!(r.bits_remaining(), 0);
        assert_eq!(BitReader::new(&[]).get_bits(0), Ok(0));
    }

    proptest! {
        #[test]
        fn word_reader_reads_what_the_bit_reader_reads(
            bytes in proptest::collection::vec(any::<u8>(), 0..40),
            widths in proptest::collection::vec(0u32..=57, 0..60)
        ) {
            let mut slow = BitReader::new(&bytes);
            let mut fast = WordReader::new(&bytes);
            for (k, n) in widths.into_iter().enumerate() {
                // Both read zeros past the end; every other read without a branch on n.
                let expected = slow.peek_bits(n);
                if k % 2 == 0 {
                    prop_assert_eq!(fast.get_bits(n), expected);
                } else {
                    fast.refill();
                    prop_assert_eq!(fast.take_refilled(n), expected);
                }
                if slow.consume(n).is_err() {
                    prop_assert!(fast.overrun());
                    break;
                }
                prop_assert!(!fast.overrun());
                prop_assert_eq!(fast.position(), slow.position());
                prop_assert_eq!(fast.bits_remaining(), slow.bits_remaining());
            }
        }

        #[test]
        fn writer_reader_and_counter_agree(
            fields in proptest::collection::vec((any::<u64>(), 0u32..=64), 0..64)
        ) {
            let mut w = BitWriter::new();
            let mut c = BitCounter::new();
            for &(v, n) in &fields {
                w.put_bits(v, n);
                c.put_bits(v, n);
                prop_assert_eq!(w.bits(), c.bits());
            }
            let bytes = w.finish();
            prop_assert_eq!(bytes.len() as u64, c.bytes());
            let mut r = BitReader::new(&bytes);
            for &(v, n) in &fields {
                let peeked = r.peek_bits(n);
                let got = r.get_bits(n).unwrap();
                prop_assert_eq!(peeked, got);
                prop_assert_eq!(got, v & low_mask(n));
            }
            prop_assert!(r.bits_remaining() < 8);
        }
    }
}
