//! Networks of a test's own making, and faults in them: each host (the learner, a worker) runs
//! in a network namespace joined to the test's namespace by a veth pair with its own /30; a
//! [`FaultProxy`] in the test's namespace carries a worker's connections to the learner and
//! injects one-way delay, a bandwidth cap, cut connections and half-open ones (bytes held,
//! sockets open); [`Lab::partition`] drops a host's packets with iptables rules in a chain of the
//! lab's own. Every namespace, link and rule is the lab's and goes when it drops.
//!
//! Needs root, `ip` and `iptables`: [`Lab::new`] returns `None` (the caller skips, saying so)
//! where creating a namespace is refused, unless `SOCIALFLOW_REQUIRE_NETNS` is set
//! (`tests/run.sh` sets it when run as root). Must not: touch any namespace, link or rule it did
//! not create.

use std::net::{Ipv4Addr, SocketAddr};
use std::path::Path;
use std::process::Command;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, watch};

use crate::Proc;

fn run(cmd: &str, args: &[&str]) -> Result<(), String> {
    let out = Command::new(cmd).args(args).output().map_err(|e| format!("{cmd}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!("{cmd} {}: {}", args.join(" "), String::from_utf8_lossy(&out.stderr).trim()))
    }
}

fn must(cmd: &str, args: &[&str]) {
    if let Err(e) = run(cmd, args) {
        panic!("{e}");
    }
}

/// A host: a network namespace with one veth link to the test's namespace.
#[derive(Clone, Debug)]
pub struct Host {
    /// The namespace's name (`ip netns exec <ns>`).
    pub ns: String,
    /// The host's address inside its namespace.
    pub ip: Ipv4Addr,
    /// The test namespace's end of the link (the host's gateway).
    pub gw: Ipv4Addr,
    link: String,
}

impl Host {
    /// Starts `bin` with `args` inside the namespace, output to `log`.
    pub fn spawn(&self, bin: &Path, args: &[&str], envs: &[(&str, &str)], log: &Path) -> Proc {
        let bin = bin.display().to_string();
        let mut all = vec!["netns", "exec", self.ns.as_str(), bin.as_str()];
        all.extend_from_slice(args);
        Proc::spawn_logged(Path::new("ip"), &all, envs, log)
    }
}

/// The namespaces, links and partition rules of one test.
pub struct Lab {
    tag: String,
    chain: String,
    hosts: Vec<Host>,
    net: u8,
}

impl Lab {
    /// A new lab, or `None` where namespaces cannot be made (not root, no `ip`/`iptables`).
    pub fn new() -> Option<Self> {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let pid = std::process::id();
        let tag = format!("sf{}{}", pid % 100_000, (b'a' + (n % 26) as u8) as char);
        // 10.<net>.<host>.0/30: one /16 per lab, apart from other test processes' labs.
        let net = 150 + ((pid.wrapping_mul(31) + n * 7) % 100) as u8;
        let chain = format!("SF-{}", tag.to_uppercase());
        let ok = run("ip", &["netns", "add", &format!("{tag}-probe")])
            .and_then(|()| run("ip", &["netns", "del", &format!("{tag}-probe")]))
            .and_then(|()| run("iptables", &["-N", &chain]));
        if let Err(e) = ok {
            assert!(
                std::env::var_os("SOCIALFLOW_REQUIRE_NETNS").is_none(),
                "SOCIALFLOW_REQUIRE_NETNS is set but the network lab cannot be made: {e}"
            );
            eprintln!("cannot make network namespaces ({e})");
            return None;
        }
        for hook in ["INPUT", "OUTPUT", "FORWARD"] {
            must("iptables", &["-I", hook, "-j", &chain]);
        }
        Some(Self { tag, chain, hosts: Vec::new(), net })
    }

    /// A new host named `name` (for logs) with its namespace and link.
    pub fn host(&mut self, name: &str) -> Host {
        let k = self.hosts.len() as u8 + 1;
        let ns = format!("{}-{name}", self.tag);
        let (link, peer) = (format!("{}{k}", self.tag), format!("{}{k}p", self.tag));
        let gw = Ipv4Addr::new(10, self.net, k, 1);
        let ip = Ipv4Addr::new(10, self.net, k, 2);
        must("ip", &["netns", "add", &ns]);
        must("ip", &["link", "add", &link, "type", "veth", "peer", "name", &peer]);
        must("ip", &["link", "set", &peer, "netns", &ns]);
        must("ip", &["addr", "add", &format!("{gw}/30"), "dev", &link]);
        must("ip", &["link", "set", &link, "up"]);
        let inside = |args: &[&str]| {
            let mut all = vec!["netns", "exec", ns.as_str(), "ip"];
            all.extend_from_slice(args);
            must("ip", &all);
        };
        inside(&["link", "set", "lo", "up"]);
        inside(&["addr", "add", &format!("{ip}/30"), "dev", &peer]);
        inside(&["link", "set", &peer, "up"]);
        inside(&["route", "add", "default", "via", &gw.to_string()]);
        let h = Host { ns, ip, gw, link };
        self.hosts.push(h.clone());
        h
    }

    fn rules(&self, h: &Host, op: &str) {
        for dir in ["-s", "-d"] {
            must("iptables", &[op, &self.chain, dir, &h.ip.to_string(), "-j", "DROP"]);
        }
    }

    /// Drops every packet to and from `h` (a partition: no RST, no ICMP; connections hang).
    pub fn partition(&self, h: &Host) {
        self.rules(h, "-A");
    }

    /// Lets `h`'s packets through again.
    pub fn heal(&self, h: &Host) {
        self.rules(h, "-D");
    }
}

impl Drop for Lab {
    fn drop(&mut self) {
        for hook in ["INPUT", "OUTPUT", "FORWARD"] {
            let _ = run("iptables", &["-D", hook, "-j", &self.chain]);
        }
        let _ = run("iptables", &["-F", &self.chain]);
        let _ = run("iptables", &["-X", &self.chain]);
        for h in &self.hosts {
            let _ = run("ip", &["link", "del", &h.link]);
            let _ = run("ip", &["netns", "del", &h.ns]);
        }
    }
}

/// What a [`FaultProxy`] does to the bytes it carries, in each direction.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Faults {
    /// Added to every byte's trip, one way.
    pub delay_ms: u64,
    /// The most bits per second each direction of each connection carries (`None`: no cap).
    pub rate_bps: Option<u64>,
    /// Hold every byte (sockets stay open, nothing arrives): a half-open link.
    pub stalled: bool,
}

/// A TCP proxy in the test's namespace between one worker and the learner.
pub struct FaultProxy {
    /// Where the worker connects.
    pub addr: SocketAddr,
    faults: watch::Sender<Faults>,
    cuts: watch::Sender<u64>,
    bytes: Arc<AtomicU64>,
    _rt: tokio::runtime::Runtime,
}

impl FaultProxy {
    /// Listens on `listen` (port 0: any) and carries each connection to `upstream`.
    pub fn start(listen: SocketAddr, upstream: SocketAddr) -> Self {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("proxy runtime");
        let listener = rt.block_on(TcpListener::bind(listen)).expect("proxy listen");
        let addr = listener.local_addr().expect("proxy address");
        let (faults, faults_rx) = watch::channel(Faults::default());
        let (cuts, cuts_rx) = watch::channel(0u64);
        let bytes = Arc::new(AtomicU64::new(0));
        let b = bytes.clone();
        rt.spawn(async move {
            while let Ok((down, _)) = listener.accept().await {
                let Ok(up) = TcpStream::connect(upstream).await else { continue };
                tokio::spawn(carry(down, up, faults_rx.clone(), cuts_rx.clone(), b.clone()));
            }
        });
        Self { addr, faults, cuts, bytes, _rt: rt }
    }

    pub fn set(&self, f: Faults) {
        let _ = self.faults.send(f);
    }

    /// Resets every open connection (both ends see it end at once); new ones are accepted.
    pub fn cut(&self) {
        self.cuts.send_modify(|n| *n += 1);
    }

    /// Bytes carried so far, both directions.
    pub fn bytes(&self) -> u64 {
        self.bytes.load(Ordering::Relaxed)
    }
}

/// Both directions of one connection until either end closes or the proxy cuts it.
async fn carry(
    down: TcpStream,
    up: TcpStream,
    faults: watch::Receiver<Faults>,
    mut cuts: watch::Receiver<u64>,
    bytes: Arc<AtomicU64>,
) {
    let _ = (down.set_nodelay(true), up.set_nodelay(true));
    // Handles on the same sockets, to shut them down when the proxy cuts the connection.
    let (Ok((down, down_handle)), Ok((up, up_handle))) = (handle(down), handle(up)) else {
        return;
    };
    let (dr, dw) = down.into_split();
    let (ur, uw) = up.into_split();
    let a = tokio::spawn(pump(dr, uw, faults.clone(), bytes.clone()));
    let b = tokio::spawn(pump(ur, dw, faults, bytes));
    let (stop_a, stop_b) = (a.abort_handle(), b.abort_handle());
    let start = *cuts.borrow_and_update();
    let cut = async {
        while cuts.changed().await.is_ok() {
            if *cuts.borrow() != start {
                return;
            }
        }
        std::future::pending::<()>().await
    };
    tokio::select! {
        _ = cut => {
            // Both ends see the connection end at once, whatever is in flight.
            let _ = down_handle.shutdown(std::net::Shutdown::Both);
            let _ = up_handle.shutdown(std::net::Shutdown::Both);
            stop_a.abort();
            stop_b.abort();
        }
        _ = async { let _ = tokio::join!(a, b); } => {}
    }
}

/// The stream back, with a second handle on its socket.
fn handle(s: TcpStream) -> std::io::Result<(TcpStream, std::net::TcpStream)> {
    let s = s.into_std()?;
    let h = s.try_clone()?;
    Ok((TcpStream::from_std(s)?, h))
}

/// One direction: reads as fast as the sender writes and the queue allows, delivers each chunk
/// `delay_ms` after it was read, no faster than `rate_bps`, nothing while stalled.
async fn pump(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    faults: watch::Receiver<Faults>,
    bytes: Arc<AtomicU64>,
) {
    // 256 chunks of up to 16 KiB in flight: enough for 100 ms at well over 100 Mbit/s.
    let (tx, mut rx) = mpsc::channel::<(Instant, Vec<u8>)>(256);
    let reader = tokio::spawn(async move {
        let mut buf = vec![0u8; 16 << 10];
        loop {
            match from.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => {
                    if tx.send((Instant::now(), buf[..n].to_vec())).await.is_err() {
                        return;
                    }
                }
            }
        }
    });
    let mut next_free = Instant::now();
    while let Some((read_at, chunk)) = rx.recv().await {
        loop {
            let f = *faults.borrow();
            if !f.stalled {
                tokio::time::sleep_until((read_at + Duration::from_millis(f.delay_ms)).into())
                    .await;
                if let Some(bps) = f.rate_bps {
                    let now = Instant::now();
                    next_free = next_free.max(now);
                    tokio::time::sleep_until(next_free.into()).await;
                    next_free += Duration::from_secs_f64(chunk.len() as f64 * 8.0 / bps as f64);
                }
                if !faults.borrow().stalled {
                    break;
                }
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        if to.write_all(&chunk).await.is_err() {
            break;
        }
        bytes.fetch_add(chunk.len() as u64, Ordering::Relaxed);
    }
    reader.abort();
    let _ = to.shutdown().await;
}
