//! Hosts for end-to-end tests: network namespaces joined by a bridge (iproute2, as root), each
//! with `/etc/netns/NS/hosts` so hosts find each other by name, links limited with `tc tbf`, and
//! the real binary (or any program) started inside them.

use std::io::{BufRead, BufReader};
use std::os::fd::AsFd;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_wavesplat");

/// Runs a command that sets up the network; panics with its output and what it needs.
pub fn setup(program: &str, args: &[&str]) {
    let out = Command::new(program)
        .args(args)
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "running {program}: {e}. These tests need root and iproute2 (`ip netns`, \
             `tc`); set WAVESPLAT_SKIP_NETNS=1 to skip it knowingly"
            )
        });
    assert!(
        out.status.success(),
        "`{program} {}` failed: {}. These tests need root and iproute2 (`ip netns`, \
         `tc`); set WAVESPLAT_SKIP_NETNS=1 to skip it knowingly",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr).trim()
    );
}

/// Network namespaces joined by a bridge in a namespace of its own, and the processes started
/// in them (killed, and the namespaces removed, on drop).
pub struct Net {
    tag: String,
    subnet: String,
    hosts: Vec<&'static str>,
    procs: Vec<u32>,
    /// Servers and workers that run until the end of the test.
    kept: Vec<Child>,
}

impl Net {
    /// A host's address.
    pub fn ip_of(&self, host: &str) -> String {
        let i = self.hosts.iter().position(|h| *h == host).unwrap();
        format!("{}.{}", self.subnet, 10 + i)
    }

    /// A host's namespace name.
    pub fn ns(&self, host: &str) -> String {
        format!("{}-{host}", self.tag)
    }

    pub fn switch(&self) -> String {
        format!("{}-sw", self.tag)
    }

    /// Makes a namespace per host on `subnet` (e.g. `10.208.0`: hosts get .10, .11, … in
    /// order); `tag` (a few letters) keeps the names apart from other tests'.
    pub fn create(tag: &str, subnet: &str, hosts: &[&'static str]) -> Net {
        let tag = format!("{tag}{}", std::process::id());
        let net = Net {
            tag: tag.clone(),
            subnet: subnet.to_string(),
            hosts: hosts.to_vec(),
            procs: Vec::new(),
            kept: Vec::new(),
        };
        let sw = net.switch();
        setup("ip", &["netns", "add", &sw]);
        setup("ip", &["-n", &sw, "link", "add", "br0", "type", "bridge"]);
        setup("ip", &["-n", &sw, "link", "set", "br0", "up"]);
        let hosts_file: String = std::iter::once("127.0.0.1 localhost\n".to_string())
            .chain(hosts.iter().map(|h| format!("{} {h}\n", net.ip_of(h))))
            .collect();
        for (i, host) in hosts.iter().enumerate() {
            let ns = net.ns(host);
            setup("ip", &["netns", "add", &ns]);
            let a = format!("{tag}a{i}");
            let b = format!("{tag}b{i}");
            setup(
                "ip",
                &["link", "add", &a, "type", "veth", "peer", "name", &b],
            );
            setup("ip", &["link", "set", &a, "netns", &ns]);
            setup("ip", &["-n", &ns, "link", "set", &a, "name", "eth0"]);
            setup("ip", &["link", "set", &b, "netns", &sw]);
            setup("ip", &["-n", &sw, "link", "set", &b, "master", "br0", "up"]);
            let addr = format!("{}/24", net.ip_of(host));
            setup("ip", &["-n", &ns, "addr", "add", &addr, "dev", "eth0"]);
            setup("ip", &["-n", &ns, "link", "set", "eth0", "up"]);
            setup("ip", &["-n", &ns, "link", "set", "lo", "up"]);
            let etc = PathBuf::from("/etc/netns").join(&ns);
            std::fs::create_dir_all(&etc).unwrap();
            std::fs::write(etc.join("hosts"), &hosts_file).unwrap();
        }
        net
    }

    /// Limits the link of `host` to `rate` (tc syntax, e.g. `1mbit`) in both directions: on
    /// its own end of the veth and on the bridge's.
    pub fn limit(&self, host: &str, rate: &str) {
        let i = self.hosts.iter().position(|h| *h == host).unwrap();
        let b = format!("{}b{i}", self.tag);
        for (ns, dev) in [(self.ns(host), "eth0".to_string()), (self.switch(), b)] {
            setup(
                "ip",
                &[
                    "netns", "exec", &ns, "tc", "qdisc", "add", "dev", &dev, "root", "tbf", "rate",
                    rate, "burst", "16kb", "latency", "400ms",
                ],
            );
        }
    }

    /// `program ARGS` on `host`, in `dir`.
    pub fn program(&self, host: &str, dir: &Path, program: &str, args: &[&str]) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", &self.ns(host), program])
            .args(args)
            .current_dir(dir);
        c
    }

    /// `wavesplat ARGS` on `host`, in `dir`, with `token` as its WAVESPLAT_TOKEN.
    pub fn command(&self, host: &str, dir: &Path, args: &[&str], token: Option<&str>) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", &self.ns(host), BIN])
            .args(args)
            .current_dir(dir)
            .env_remove("WAVESPLAT_TOKEN")
            .env_remove("WAVESPLAT_CA")
            .env_remove("WAVESPLAT_TOKENS_FILE");
        if let Some(t) = token {
            c.env("WAVESPLAT_TOKEN", t);
        }
        c
    }

    /// Runs `wavesplat ARGS` on `host` in `dir` to its end.
    pub fn run(&self, host: &str, dir: &Path, args: &[&str], token: Option<&str>) -> Output {
        self.command(host, dir, args, token).output().unwrap()
    }

    /// Starts `wavesplat ARGS` on `host`, its stderr in `dir/NAME.log`.
    pub fn spawn(
        &mut self,
        host: &str,
        dir: &Path,
        name: &str,
        args: &[&str],
        token: Option<&str>,
    ) -> Child {
        self.spawn_with_env(host, dir, name, args, token, &[])
    }

    /// [`Net::spawn`] with more environment variables.
    pub fn spawn_with_env(
        &mut self,
        host: &str,
        dir: &Path,
        name: &str,
        args: &[&str],
        token: Option<&str>,
        env: &[(&str, &str)],
    ) -> Child {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join(format!("{name}.log")))
            .unwrap();
        let child = self
            .command(host, dir, args, token)
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap();
        self.procs.push(child.id());
        child
    }

    /// Starts a server on `host` and waits for its `listening on` line (its stderr goes to
    /// `dir/NAME.log`).
    pub fn serve(
        &mut self,
        host: &str,
        dir: &Path,
        name: &str,
        args: &[&str],
        token: Option<&str>,
    ) -> Child {
        self.serve_with_env(host, dir, name, args, token, &[])
    }

    /// [`Net::serve`] with more environment variables.
    pub fn serve_with_env(
        &mut self,
        host: &str,
        dir: &Path,
        name: &str,
        args: &[&str],
        token: Option<&str>,
        env: &[(&str, &str)],
    ) -> Child {
        let mut child = self.spawn_with_env(host, dir, name, args, token, env);
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        assert!(
            line.starts_with("listening on "),
            "{name} on {host} did not start: {line:?}; its log: {}",
            std::fs::read_to_string(dir.join(format!("{name}.log"))).unwrap_or_default()
        );
        child
    }

    /// Keeps `child` running until the test ends (killed and waited for then).
    pub fn keep(&mut self, child: Child) {
        self.kept.push(child);
    }

    /// Runs `f` on a thread inside `host`'s network namespace (its sockets are that host's).
    pub fn on_host<T: Send + 'static>(
        &self,
        host: &str,
        f: impl FnOnce() -> T + Send + 'static,
    ) -> T {
        let path = format!("/var/run/netns/{}", self.ns(host));
        std::thread::spawn(move || {
            let ns = std::fs::File::open(&path).unwrap();
            // setns(2) moves only this thread into the namespace.
            rustix::thread::move_into_link_name_space(
                ns.as_fd(),
                Some(rustix::thread::LinkNameSpaceType::Network),
            )
            .unwrap_or_else(|e| panic!("setns {path}: {e}"));
            f()
        })
        .join()
        .unwrap()
    }
}

impl Drop for Net {
    fn drop(&mut self) {
        for pid in &self.procs {
            let _ = Command::new("kill").args(["-9", &pid.to_string()]).output();
        }
        for c in &mut self.kept {
            let _ = c.wait();
        }
        for host in &self.hosts {
            let ns = self.ns(host);
            let _ = Command::new("ip").args(["netns", "del", &ns]).output();
            let _ = std::fs::remove_dir_all(PathBuf::from("/etc/netns").join(&ns));
        }
        let _ = Command::new("ip")
            .args(["netns", "del", &self.switch()])
            .output();
    }
}
