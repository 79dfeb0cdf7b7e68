//! A throwaway PostgreSQL server for the queue's tests and benches: Debian's (or any) server
//! binaries, `initdb` into a temporary directory, the postmaster started as a child on a free
//! loopback port with password (SCRAM) authentication over TCP, stopped (or crashed and started
//! again) by the caller, and killed when dropped. Run as root (as CI is), the server runs as the
//! `postgres` user (PostgreSQL refuses to run as root). [`PostgresSetup`] puts it on another
//! address, behind TLS, or inside a network namespace (a database host of the deployment
//! tests).

use anyhow::{anyhow, bail, Context, Result};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The superuser's password in every test server.
pub const PASSWORD: &str = "wavesplat-test-password";

/// How a test server listens.
#[derive(Debug, Clone, Default)]
pub struct PostgresSetup {
    /// The address to listen on (default `127.0.0.1`).
    pub listen: Option<String>,
    /// A certificate and key (PEM files): TLS on, and TCP connections without it refused.
    pub tls: Option<(PathBuf, PathBuf)>,
    /// Run the server inside this network namespace (`ip netns exec`; needs root).
    pub netns: Option<String>,
}

/// A PostgreSQL server in a temporary directory.
pub struct PostgresServer {
    dir: tempfile::TempDir,
    bin: PathBuf,
    port: u16,
    owner: Option<(u32, u32)>,
    setup: PostgresSetup,
    child: Option<Child>,
}

/// The directory of the newest installed server's programs: `/usr/lib/postgresql/N/bin`
/// (Debian), else wherever `initdb` is on the PATH.
pub fn server_bin_dir() -> Result<PathBuf> {
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let v: u32 = e.file_name().to_str()?.parse().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").exists().then_some((v, bin))
        })
        .collect();
    versions.sort();
    if let Some((_, bin)) = versions.pop() {
        return Ok(bin);
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .find(|d| d.join("initdb").exists() && d.join("postgres").exists())
        .ok_or_else(|| {
            anyhow!(
                "no PostgreSQL server found (no /usr/lib/postgresql/*/bin/initdb, no initdb on \
                 the PATH): install Debian's `postgresql` package"
            )
        })
}

fn id_of(flag: &str, user: &str) -> Result<u32> {
    let out = Command::new("id").args([flag, user]).output()?;
    String::from_utf8_lossy(&out.stdout)
        .trim()
        .parse()
        .with_context(|| format!("no user {user:?} to run PostgreSQL as"))
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

impl PostgresServer {
    /// Creates a cluster (`initdb`) on loopback without TLS and starts it.
    pub fn start() -> Result<PostgresServer> {
        PostgresServer::start_with(PostgresSetup::default())
    }

    /// Creates a cluster (`initdb`) as `setup` says and starts it.
    pub fn start_with(setup: PostgresSetup) -> Result<PostgresServer> {
        let bin = server_bin_dir()?;
        let dir = tempfile::Builder::new().prefix("wavesplat-pg").tempdir()?;
        let root = Command::new("id").arg("-u").output()?.stdout == b"0\n";
        let owner = if root {
            Some((id_of("-u", "postgres")?, id_of("-g", "postgres")?))
        } else {
            None
        };
        let pwfile = dir.path().join("pw");
        std::fs::write(&pwfile, PASSWORD)?;
        for p in [dir.path(), &pwfile] {
            chown(p, owner)?;
        }
        let mut server = PostgresServer {
            bin,
            port: free_port()?,
            owner,
            setup,
            child: None,
            dir,
        };
        let data = server.data_dir();
        let out = server
            .command("initdb")
            .args(["-D", data.to_str().context("utf-8 temp path")?])
            .args(["-U", "postgres", "-E", "UTF8", "--no-sync"])
            .args(["--auth-local=trust", "--auth-host=scram-sha-256"])
            .arg(format!("--pwfile={}", pwfile.display()))
            .output()
            .context("running initdb")?;
        if !out.status.success() {
            bail!(
                "initdb failed: {}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        // Password authentication over TCP from anywhere; with TLS, only over TLS.
        let host = if server.setup.tls.is_some() {
            "hostssl"
        } else {
            "host"
        };
        std::fs::write(
            data.join("pg_hba.conf"),
            format!(
                "local all all trust\n{host} all all 0.0.0.0/0 scram-sha-256\n\
                 {host} all all ::/0 scram-sha-256\n"
            ),
        )?;
        if let Some((cert, key)) = server.setup.tls.clone() {
            for (from, to) in [(cert, "server.crt"), (key, "server.key")] {
                let dest = data.join(to);
                std::fs::copy(&from, &dest)
                    .with_context(|| format!("copying {}", from.display()))?;
                std::fs::set_permissions(
                    &dest,
                    std::os::unix::fs::PermissionsExt::from_mode(0o600),
                )?;
                chown(&dest, server.owner)?;
            }
        }
        server.resume()?;
        Ok(server)
    }

    fn data_dir(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    fn command(&self, program: &str) -> Command {
        let mut c = Command::new(self.bin.join(program));
        if let Some((uid, gid)) = self.owner {
            c.uid(uid).gid(gid);
        }
        c.current_dir(self.dir.path());
        c
    }

    /// Starts the postmaster (again, after [`PostgresServer::crash`] or
    /// [`PostgresServer::stop`]) on the same port and data, and waits until it accepts
    /// connections.
    pub fn resume(&mut self) -> Result<()> {
        if self.child.is_some() {
            return Ok(());
        }
        let log = std::fs::File::create(self.dir.path().join("server.log"))?;
        let data = self.data_dir();
        let postgres = self.bin.join("postgres");
        let mut command = match (&self.setup.netns, self.owner) {
            (Some(ns), Some((uid, gid))) => {
                // `ip netns exec` needs root; setpriv then drops to the server's user and
                // execs it, so the child is the postmaster itself.
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns, "setpriv"])
                    .arg(format!("--reuid={uid}"))
                    .arg(format!("--regid={gid}"))
                    .args(["--clear-groups", "--"])
                    .arg(&postgres);
                c.current_dir(self.dir.path());
                c
            }
            (Some(_), None) => bail!("a server in a network namespace needs root"),
            (None, _) => self.command("postgres"),
        };
        let listen = self.setup.listen.as_deref().unwrap_or("127.0.0.1");
        command
            .args(["-D", data.to_str().context("utf-8 temp path")?])
            .args(["-p", &self.port.to_string()])
            .args(["-c", &format!("listen_addresses={listen}")])
            .args([
                "-c",
                &format!("unix_socket_directories={}", self.dir.path().display()),
            ])
            .args(["-c", "max_connections=200", "-c", "fsync=off"]);
        if self.setup.tls.is_some() {
            command.args(["-c", "ssl=on"]);
        }
        let child = command
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .context("starting postgres")?;
        self.child = Some(child);
        let start = Instant::now();
        loop {
            let ready = Command::new(self.bin.join("pg_isready"))
                .args(["-h", &self.dir.path().display().to_string()])
                .args(["-p", &self.port.to_string(), "-q"])
                .status()?;
            if ready.success() {
                return Ok(());
            }
            if let Some(status) = self
                .child
                .as_mut()
                .and_then(|c| c.try_wait().ok().flatten())
            {
                self.child = None;
                bail!("postgres exited ({status}): {}", self.log());
            }
            if start.elapsed() > Duration::from_secs(60) {
                bail!(
                    "postgres did not accept connections in 60 s: {}",
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The server's log so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("server.log")).unwrap_or_default()
    }

    fn signal(&mut self, signal: &str) -> Result<()> {
        if let Some(mut child) = self.child.take() {
            Command::new("kill")
                .args([signal, &child.id().to_string()])
                .status()?;
            child.wait()?;
        }
        Ok(())
    }

    /// Crashes the server as a power cut would look to it (an immediate shutdown: backends
    /// killed, no checkpoint; the next start recovers from the log).
    pub fn crash(&mut self) -> Result<()> {
        self.signal("-QUIT")
    }

    /// Stops the server cleanly (fast shutdown: sessions are disconnected).
    pub fn stop(&mut self) -> Result<()> {
        self.signal("-INT")
    }

    /// The TCP port.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Creates database `name` (empty).
    pub fn create_database(&self, name: &str) -> Result<()> {
        self.psql("postgres", &format!("CREATE DATABASE \"{name}\""))
            .with_context(|| format!("creating database {name}"))?;
        Ok(())
    }

    /// Runs one SQL statement in database `db` with `psql` and returns its unaligned output.
    pub fn psql(&self, db: &str, sql: &str) -> Result<String> {
        let out = Command::new(self.bin.join("psql"))
            .args(["-h", &self.dir.path().display().to_string()])
            .args(["-p", &self.port.to_string(), "-U", "postgres", "-d", db])
            .args(["-v", "ON_ERROR_STOP=1", "-q", "-A", "-t", "-c", sql])
            .output()
            .context("running psql")?;
        if !out.status.success() {
            bail!("{sql}: {}", String::from_utf8_lossy(&out.stderr));
        }
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    }

    /// `postgres://postgres@127.0.0.1:PORT/DB` without the password (give it by `PGPASSWORD`).
    pub fn url(&self, db: &str) -> String {
        self.url_at("127.0.0.1", db)
    }

    /// `postgres://postgres@HOST:PORT/DB` without the password.
    pub fn url_at(&self, host: &str, db: &str) -> String {
        format!("postgres://postgres@{host}:{}/{db}", self.port)
    }

    /// [`PostgresServer::url`] with the password in it.
    pub fn url_with_password(&self, db: &str) -> String {
        format!(
            "postgres://postgres:{PASSWORD}@127.0.0.1:{}/{db}",
            self.port
        )
    }
}

fn chown(path: &Path, owner: Option<(u32, u32)>) -> Result<()> {
    if let Some((uid, gid)) = owner {
        std::os::unix::fs::chown(path, Some(uid), Some(gid))
            .with_context(|| format!("chown {}", path.display()))?;
    }
    Ok(())
}

impl Drop for PostgresServer {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            // Immediate shutdown: the postmaster takes its backends down with it (SIGKILL
            // would leave them holding shared memory).
            let _ = Command::new("kill")
                .args(["-QUIT", &child.id().to_string()])
                .status();
            let _ = child.wait();
        }
    }
}
