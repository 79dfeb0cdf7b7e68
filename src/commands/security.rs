//! Security options shared by the servers and the clients: TLS certificates, tokens and the
//! `--insecure` override for servers; the CA and the token for clients. Secrets are never
//! command-line arguments (they would show in `ps` and shell history): servers read a token
//! file (`--tokens FILE` or the file named by `WAVESPLAT_TOKENS_FILE`), clients a file
//! (`--token-file FILE`) or `WAVESPLAT_TOKEN`.

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::sync::Arc;
use wavesplat_net::{ConnectOptions, Credentials, Security, Tokens};

/// Environment variable naming the server's token file.
pub const TOKENS_FILE_ENV: &str = "WAVESPLAT_TOKENS_FILE";
/// Environment variable naming the clients' CA certificate.
pub const CA_ENV: &str = "WAVESPLAT_CA";

/// How a server protects itself.
#[derive(Args, Debug, Clone, Default)]
pub struct ServerSecurityArgs {
    /// Serve TLS with this PEM certificate chain (with --tls-key).
    #[arg(long, requires = "tls_key", value_name = "PEM")]
    pub tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert", value_name = "PEM")]
    pub tls_key: Option<PathBuf>,
    /// Require tokens from this file: one `IDENTITY ROLES SECRET` a line, roles from read,
    /// ingest, write, worker, admin (default: the file named by WAVESPLAT_TOKENS_FILE, else none).
    #[arg(long, value_name = "FILE")]
    pub tokens: Option<PathBuf>,
    /// Serve on a non-loopback address without TLS and tokens (trusted networks only).
    #[arg(long)]
    pub insecure: bool,
}

impl ServerSecurityArgs {
    /// The server's security settings.
    pub fn security(&self) -> Result<Security> {
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => Some(wavesplat_net::tls::server_tls(cert, key)?),
            _ => None,
        };
        let file = self
            .tokens
            .clone()
            .or_else(|| std::env::var_os(TOKENS_FILE_ENV).map(PathBuf::from));
        let tokens = match file {
            Some(f) => {
                let t = Tokens::load(&f)?;
                if t.is_empty() {
                    anyhow::bail!("the token file {} holds no token", f.display());
                }
                Some(Arc::new(t))
            }
            None => None,
        };
        Ok(Security {
            tls,
            tokens,
            insecure: self.insecure,
        })
    }
}

/// How a client reaches a service.
#[derive(Args, Debug, Clone, Default)]
pub struct ClientSecurityArgs {
    /// PEM CA certificate to verify https:// servers with (default: WAVESPLAT_CA, else the
    /// system's roots).
    #[arg(long, value_name = "PEM")]
    pub ca: Option<PathBuf>,
    /// Read the token to send from this file (default: the WAVESPLAT_TOKEN environment
    /// variable, else none).
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
}

impl ClientSecurityArgs {
    /// The client's connection options.
    pub fn options(&self) -> Result<ConnectOptions> {
        let credentials = Credentials::from_file_or_env(self.token_file.as_deref())
            .context("reading the token")?;
        let ca = self
            .ca
            .clone()
            .or_else(|| std::env::var_os(CA_ENV).map(PathBuf::from));
        Ok(ConnectOptions { ca, credentials })
    }
}
