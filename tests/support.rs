//! Helpers for end-to-end tests: locating the built binaries and running them with a deadline.
//!
//! `cargo test --workspace` does not build other packages' binaries; `tests/run.sh` builds
//! them first. Children are killed when their deadline passes or when the handle drops.

pub mod netns;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

/// The repository root.
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Path of a workspace binary built in the same profile as this test.
pub fn bin(name: &str) -> PathBuf {
    if let Ok(p) = std::env::var(format!("SOCIALFLOW_BIN_{}", name.to_uppercase())) {
        return PathBuf::from(p);
    }
    // Every binary from one directory (e.g. a release build's, for measurements).
    if let Some(dir) = std::env::var_os("SOCIALFLOW_BIN_DIR") {
        return PathBuf::from(dir).join(name);
    }
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe.parent().and_then(Path::parent).expect("target profile dir");
    let p = dir.join(name);
    assert!(p.exists(), "{} is not built: run `cargo build --workspace --bins` first", p.display());
    p
}

/// A child process that is killed (and reaped) on drop unless it was waited for.
pub struct Proc(Option<Child>);

impl Proc {
    pub fn new(child: Child) -> Self {
        Self(Some(child))
    }

    /// Waits for exit and collects the output; fails the test past `deadline`.
    /// Output must fit the pipe buffers (these commands print little).
    pub fn output(mut self, what: &str, deadline: Duration) -> Output {
        let start = Instant::now();
        loop {
            let child = self.0.as_mut().expect("child present until waited");
            if child.try_wait().expect("try_wait").is_some() {
                return self.0.take().expect("child").wait_with_output().expect("collect output");
            }
            assert!(start.elapsed() < deadline, "{what} ran past {deadline:?}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Some(c) = self.0.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// Runs `socialflow` with `args` in the repository root; fails the test past `deadline`.
pub fn socialflow(args: &[&str], deadline: Duration) -> Output {
    socialflow_env(args, &[], deadline)
}

/// [`socialflow`] with extra environment variables.
pub fn socialflow_env(args: &[&str], envs: &[(&str, &str)], deadline: Duration) -> Output {
    let mut c = Command::new(bin("socialflow"));
    c.args(args)
        .current_dir(repo())
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    for (k, v) in envs {
        c.env(k, v);
    }
    Proc::new(c.spawn().expect("spawn socialflow"))
        .output(&format!("socialflow {args:?}"), deadline)
}

/// A free TCP port for a test's server (bound on all interfaces and released). Taken below the
/// kernel's ephemeral range (32768-60999 on Linux): a port the kernel hands out can become the
/// source port of a concurrently running test's client between this check and the server's bind
/// (a learner once died on "address already in use" that way). Each process starts at its own
/// offset and never offers a port twice.
pub fn free_port() -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    static NEXT: AtomicU32 = AtomicU32::new(0);
    const LOW: u32 = 20_000;
    const SPAN: u32 = 12_000;
    let start = std::process::id().wrapping_mul(7_919) % SPAN;
    for _ in 0..SPAN {
        let k = NEXT.fetch_add(1, Ordering::Relaxed);
        // 13 is coprime to SPAN, so the steps visit every port of the span.
        let port = LOW + start.wrapping_add(k.wrapping_mul(13)) % SPAN;
        let port = u16::try_from(port).expect("below 32000");
        if std::net::TcpListener::bind(("0.0.0.0", port)).is_ok() {
            return port;
        }
    }
    panic!("no free port in {LOW}..{}", LOW + SPAN)
}

/// A fresh scratch directory under the target dir's tmp.
pub fn scratch(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("socialflow-e2e-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("scratch dir");
    d
}

impl Proc {
    /// Spawns `bin` with `args` in the repository root, stdout and stderr appended to `log`.
    pub fn spawn_logged(bin: &Path, args: &[&str], envs: &[(&str, &str)], log: &Path) -> Self {
        let f = std::fs::OpenOptions::new().create(true).append(true).open(log).expect("log file");
        let f2 = f.try_clone().expect("log file");
        let mut c = Command::new(bin);
        c.args(args)
            .current_dir(repo())
            .env("RUST_LOG", "info")
            .stdout(Stdio::from(f))
            .stderr(Stdio::from(f2));
        for (k, v) in envs {
            c.env(k, v);
        }
        Self::new(c.spawn().unwrap_or_else(|e| panic!("spawn {}: {e}", bin.display())))
    }

    /// SIGKILL and reap.
    pub fn kill9(&mut self) {
        if let Some(mut c) = self.0.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERM, then wait up to `grace` for exit (SIGKILL after).
    pub fn terminate(&mut self, grace: Duration) -> bool {
        let Some(c) = self.0.as_mut() else { return true };
        let _ = Command::new("kill").arg("-TERM").arg(c.id().to_string()).status();
        let start = Instant::now();
        while start.elapsed() < grace {
            if c.try_wait().ok().flatten().is_some() {
                self.0 = None;
                return true;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        self.kill9();
        false
    }
}

/// Polls `f` every 100 ms until it returns `Some`, failing the test past `deadline`.
pub fn wait_for<T>(what: &str, deadline: Duration, mut f: impl FnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(start.elapsed() < deadline, "timed out after {deadline:?} waiting for {what}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A job config small enough for a debug build on 2 cores that still trains for a while.
/// `scenarios` is the inside of the TOML list, e.g. `"roundabout", "merge"`.
pub fn tiny_job(scenarios: &str, name: &str, env_steps: u64) -> String {
    format!(
        r#"name = "{name}"
[env]
scenarios = [{scenarios}]
vehicles_min = 2
vehicles_max = 3
[net]
width = 16
[sac]
batch_size = 32
warmup_steps = 200
[train]
env_steps = {env_steps}
samples_per_insert = 0.1
replay_capacity = 20000
publish_every_updates = 5
checkpoint_every_s = 1
max_policy_lag = 1000
[worker]
envs = 4
batch_transitions = 64
"#
    )
}

// The service as deployed: learner and worker processes on loopback.

pub const TOKEN: &str = "e2e-test-token-0123";
pub const TWO_MAPS: &str = r#""roundabout", "merge""#;

/// A `socialflow-learner` process on loopback ports.
pub struct Learner {
    pub proc: Proc,
    pub url: String,
    pub admin: String,
    pub cfg: PathBuf,
    pub log: PathBuf,
}

pub fn start_learner(dir: &Path, max_message_bytes: usize) -> Learner {
    start_learner_with(dir, max_message_bytes, "")
}

/// `extra`: more lines of learner config (TOML).
pub fn start_learner_with(dir: &Path, max_message_bytes: usize, extra: &str) -> Learner {
    let (g, a) = (free_port(), free_port());
    let data = dir.join("data");
    let cfg = dir.join("learner.toml");
    std::fs::write(
        &cfg,
        format!("grpc_addr = \"127.0.0.1:{g}\"\nadmin_addr = \"127.0.0.1:{a}\"\ndata_dir = \"{}\"\nscenarios_dir = \"configs/scenarios\"\nmax_message_bytes = {max_message_bytes}\nshutdown_grace_s = 60\n{extra}", data.display()),
    )
    .expect("learner config");
    let log = dir.join("learner.log");
    let proc = Proc::spawn_logged(
        &bin("socialflow-learner"),
        &["--config", &cfg.display().to_string()],
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        &log,
    );
    let l = Learner {
        proc,
        url: format!("http://127.0.0.1:{g}"),
        admin: format!("127.0.0.1:{a}"),
        cfg,
        log,
    };
    wait_for("learner readiness", Duration::from_secs(60), || {
        http_get(&l.admin, "/readyz").filter(|b| b.contains("ready"))
    });
    l
}

pub fn restart(l: &mut Learner) {
    let log = l.log.clone();
    l.proc = Proc::spawn_logged(
        &bin("socialflow-learner"),
        &["--config", &l.cfg.display().to_string()],
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        &log,
    );
    wait_for("learner readiness after restart", Duration::from_secs(60), || {
        http_get(&l.admin, "/readyz").filter(|b| b.contains("ready"))
    });
}

/// A size-limited tmpfs mounted at a directory for a test, unmounted when dropped. Needs root:
/// `None` (the caller skips, saying so) where mounting is refused, unless
/// `SOCIALFLOW_REQUIRE_TMPFS` is set (`tests/run.sh` sets it when run as root).
pub struct Tmpfs(PathBuf);

impl Tmpfs {
    pub fn mount(at: &Path, size_mb: u32) -> Option<Self> {
        std::fs::create_dir_all(at).expect("mount point");
        let ok = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size_mb}m"), "tmpfs"])
            .arg(at)
            .status()
            .is_ok_and(|s| s.success());
        assert!(
            ok || std::env::var_os("SOCIALFLOW_REQUIRE_TMPFS").is_none(),
            "SOCIALFLOW_REQUIRE_TMPFS is set but mounting a tmpfs at {} failed",
            at.display()
        );
        ok.then(|| Self(at.to_path_buf()))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

/// Fills the file system of `dir` with `dir/<name>` until a write fails with "no space" (1 MiB
/// writes, then 4 KiB ones for the rest).
pub fn fill_disk(dir: &Path, name: &str) {
    use std::io::Write;
    let mut f = std::fs::File::create(dir.join(name)).expect("filler file");
    for chunk in [1 << 20, 4096] {
        let buf = vec![0xA5u8; chunk];
        while f.write_all(&buf).and_then(|()| f.flush()).is_ok() {}
    }
    let _ = f.sync_all();
}

/// Moves the (stopped) learner's data directory `dir/data` to `dir/<to>`, as a restored backup or
/// a volume mounted elsewhere would, and points its config there.
pub fn move_data_dir(l: &Learner, dir: &Path, to: &str) {
    let (from, to) = (dir.join("data"), dir.join(to));
    std::fs::rename(&from, &to).expect("moving the data directory");
    let cfg = std::fs::read_to_string(&l.cfg).expect("learner config");
    std::fs::write(
        &l.cfg,
        cfg.replace(
            &format!("data_dir = \"{}\"", from.display()),
            &format!("data_dir = \"{}\"", to.display()),
        ),
    )
    .expect("learner config");
}

pub fn start_worker(l: &Learner, dir: &Path, k: usize) -> Proc {
    Proc::spawn_logged(
        &bin("socialflow-worker"),
        &["--learner", &l.url, "--name", &format!("w{k}"), "--max-backoff-s", "1"],
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        &dir.join(format!("worker{k}.log")),
    )
}

/// A plain HTTP/1.0 GET on the admin port; `None` on any failure.
pub fn http_get(addr: &str, path: &str) -> Option<String> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(s, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").ok()?;
    let mut out = String::new();
    s.read_to_string(&mut out).ok()?;
    (out.starts_with("HTTP/1.0 200") || out.starts_with("HTTP/1.1 200")).then_some(out)
}

/// gRPC clients of a test learner and the calls the tests repeat.
pub mod grpc {
    use std::time::Duration;

    use sf_proto::pb;
    use sf_proto::pb::experience_service_client::ExperienceServiceClient;
    use sf_proto::pb::job_service_client::JobServiceClient;
    use sf_service::auth::{AttachToken, Token};
    use tonic::service::interceptor::InterceptedService;
    use tonic::transport::Channel;

    use super::{wait_for, TOKEN};

    pub fn metric(body: &str, name: &str) -> f64 {
        body.lines()
            .filter(|l| l.starts_with(name))
            .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
            .sum()
    }

    pub fn rt() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime")
    }

    pub type Jobs = JobServiceClient<InterceptedService<Channel, AttachToken>>;
    pub type Exp = ExperienceServiceClient<InterceptedService<Channel, AttachToken>>;

    pub fn channel(rt: &tokio::runtime::Runtime, url: &str) -> Channel {
        rt.block_on(async {
            tonic::transport::Endpoint::from_shared(url.to_string()).expect("url").connect().await
        })
        .expect("connect to the learner")
    }

    pub fn jobs(rt: &tokio::runtime::Runtime, url: &str, token: Option<&str>) -> Jobs {
        let t = token.map(|t| Token::new(t, "test").expect("token"));
        JobServiceClient::with_interceptor(channel(rt, url), AttachToken::new(t))
            .max_encoding_message_size(usize::MAX)
    }

    pub fn exp(rt: &tokio::runtime::Runtime, url: &str) -> Exp {
        ExperienceServiceClient::with_interceptor(
            channel(rt, url),
            AttachToken::new(Some(Token::new(TOKEN, "test").expect("token"))),
        )
        .max_encoding_message_size(usize::MAX)
    }

    pub fn submit(rt: &tokio::runtime::Runtime, c: &mut Jobs, toml: String) -> pb::Job {
        rt.block_on(c.submit_job(pb::SubmitJobRequest { config_toml: toml }))
            .expect("submit")
            .into_inner()
    }

    pub fn get(rt: &tokio::runtime::Runtime, c: &mut Jobs, id: u64) -> pb::Job {
        rt.block_on(c.get_job(pb::GetJobRequest { job_id: id })).expect("get job").into_inner()
    }

    pub fn progress(j: &pb::Job) -> pb::JobProgress {
        j.progress.unwrap_or_default()
    }

    pub const SUCCEEDED: i32 = pb::JobState::Succeeded as i32;

    /// Polls a job until it succeeds or fails.
    pub fn wait_final(rt: &tokio::runtime::Runtime, c: &mut Jobs, id: u64, what: &str) -> pb::Job {
        wait_for(what, Duration::from_secs(600), || {
            let j = get(rt, c, id);
            (j.state == SUCCEEDED || j.state == pb::JobState::Failed as i32).then_some(j)
        })
    }

    /// Pushes one batch on a fresh stream; the status that ended it (OK if it was accepted).
    pub fn push_one(
        rt: &tokio::runtime::Runtime,
        e: &mut Exp,
        b: pb::TransitionBatch,
    ) -> tonic::Status {
        rt.block_on(async {
            let mut acks = e.push_transitions(tokio_stream::iter(vec![b])).await?.into_inner();
            while acks.message().await?.is_some() {}
            Ok::<(), tonic::Status>(())
        })
        .err()
        .unwrap_or_else(|| tonic::Status::ok(""))
    }
}
