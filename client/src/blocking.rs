//! A blocking facade over [`crate::CacheClient`] for synchronous callers (command-line tools, a
//! render loop that must not be async): each call runs on a private current-thread runtime.
//! Streams are not offered here: a caller that must not block on the network runs the async
//! stream on its own task (see the viewer's cache source).

use crate::{
    CacheClient as AsyncClient, ClientError, ConnectOptions, Ingested, Packet, PacketEntry,
    VolumeHeader, VolumeInfo, VolumeKey,
};
use wavesplat_codec::format::Header;

/// A blocking cache client.
#[derive(Debug)]
pub struct CacheClient {
    runtime: tokio::runtime::Runtime,
    inner: AsyncClient,
}

impl CacheClient {
    /// Connects to a cache at `url`.
    pub fn connect(url: &str) -> Result<CacheClient, ClientError> {
        Self::connect_with(url, &ConnectOptions::default())
    }

    /// Connects to a cache at `url` with `options` (CA, token).
    pub fn connect_with(url: &str, options: &ConnectOptions) -> Result<CacheClient, ClientError> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| ClientError::Protocol(format!("cannot start a runtime: {e}")))?;
        let inner = runtime.block_on(AsyncClient::connect_with(url, options))?;
        Ok(CacheClient { runtime, inner })
    }

    /// Every stored volume.
    pub fn list(&mut self) -> Result<Vec<VolumeInfo>, ClientError> {
        self.runtime.block_on(self.inner.list())
    }

    /// One volume's facts.
    pub fn describe(&mut self, key: &VolumeKey) -> Result<VolumeInfo, ClientError> {
        self.runtime.block_on(self.inner.describe(key))
    }

    /// A volume's header.
    pub fn header(&mut self, key: &VolumeKey) -> Result<VolumeHeader, ClientError> {
        self.runtime.block_on(self.inner.header(key))
    }

    /// A volume's packet table.
    pub fn packet_table(&mut self, key: &VolumeKey) -> Result<Vec<PacketEntry>, ClientError> {
        self.runtime.block_on(self.inner.packet_table(key))
    }

    /// Removes a volume.
    pub fn delete(&mut self, key: &VolumeKey) -> Result<u64, ClientError> {
        self.runtime.block_on(self.inner.delete(key))
    }

    /// Uploads a `.wsp` file.
    pub fn ingest(&mut self, name: &str, bytes: &[u8]) -> Result<Ingested, ClientError> {
        self.runtime.block_on(self.inner.ingest(name, bytes))
    }

    /// Uploads a `.wsp` file, taking its bytes (no copy of the file: see
    /// [`crate::CacheClient::ingest_owned`]).
    pub fn ingest_owned(&mut self, name: &str, bytes: Vec<u8>) -> Result<Ingested, ClientError> {
        self.runtime.block_on(self.inner.ingest_owned(name, bytes))
    }

    /// Uploads a `.wsp` file from disk without holding it (see
    /// [`crate::CacheClient::ingest_file`]).
    pub fn ingest_file(
        &mut self,
        name: &str,
        file: std::fs::File,
    ) -> Result<Ingested, ClientError> {
        self.runtime.block_on(self.inner.ingest_file(name, file))
    }

    /// The header and the first packets in file order, up to `max_bytes`.
    pub fn first_packets(
        &mut self,
        key: &VolumeKey,
        max_bytes: u64,
    ) -> Result<(Header, Vec<Packet>), ClientError> {
        self.runtime
            .block_on(self.inner.first_packets(key, max_bytes))
    }
}
