//! The real `wavesplat` binary started as a server, as a user starts it: a child process bound
//! to port 0 that announces `listening on ADDR` as its first line of stdout. The caller names
//! the binary (`env!("CARGO_BIN_EXE_wavesplat")` in the workspace's tests). The child is killed
//! when dropped.

use anyhow::{bail, Context, Result};
use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};

/// A server process and the address it announced.
pub struct ServerProcess {
    /// The child; killed when this is dropped (`None` once handed out by `into_parts`).
    child: Option<Child>,
    /// `HOST:PORT` from its first line.
    pub addr: String,
}

impl ServerProcess {
    /// Starts `bin ARGS` with its stderr discarded (`WAVESPLAT_TOKENS_FILE` removed from its
    /// environment, so a caller's tokens never leak into a test) and waits for its first line.
    pub fn spawn(bin: &Path, args: &[&str]) -> Result<ServerProcess> {
        ServerProcess::spawn_with(bin, args, Stdio::null())
    }

    /// [`ServerProcess::spawn`] keeping stderr: [`ServerProcess::stop_and_read_stderr`] reads it.
    pub fn spawn_with_stderr(bin: &Path, args: &[&str]) -> Result<ServerProcess> {
        ServerProcess::spawn_with(bin, args, Stdio::piped())
    }

    fn spawn_with(bin: &Path, args: &[&str], stderr: Stdio) -> Result<ServerProcess> {
        let mut command = Command::new(bin);
        command.args(args).stderr(stderr);
        ServerProcess::start(command)
    }

    /// Starts a prepared command (its environment, its stderr as the caller set them;
    /// `WAVESPLAT_TOKENS_FILE` removed) and waits for its `listening on ADDR` line.
    pub fn start(mut command: Command) -> Result<ServerProcess> {
        let args: Vec<String> = command
            .get_args()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        let mut child = command
            .env_remove("WAVESPLAT_TOKENS_FILE")
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting {}", command.get_program().to_string_lossy()))?;
        let mut line = String::new();
        if let Some(out) = child.stdout.take() {
            BufReader::new(out)
                .read_line(&mut line)
                .context("reading the server's first line")?;
        }
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            let _ = child.kill();
            let _ = child.wait();
            bail!("the server {args:?} said {line:?} instead of `listening on ADDR`");
        };
        Ok(ServerProcess {
            addr: addr.to_string(),
            child: Some(child),
        })
    }

    /// `http://ADDR`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// SIGKILL, then waits for the exit: no shutdown path of the server runs.
    pub fn kill(mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// The child process and the address, for a caller that stops it itself (a signal, a
    /// wait for its exit status).
    pub fn into_parts(mut self) -> (Child, String) {
        let child = self.child.take().expect("a server process holds its child");
        (child, std::mem::take(&mut self.addr))
    }

    /// Kills the server and returns what it wrote on stderr (with
    /// [`ServerProcess::spawn_with_stderr`]).
    pub fn stop_and_read_stderr(self) -> String {
        let (child, _) = self.into_parts();
        stop_and_read_stderr(child)
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// Kills a server child and returns what it wrote on stderr (when it was piped).
pub fn stop_and_read_stderr(mut child: Child) -> String {
    let _ = child.kill();
    let _ = child.wait();
    let mut err = String::new();
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    err
}
