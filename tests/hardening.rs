//! The learner against clients that probe, race and misbehave: health and reflection without a
//! token, metrics that `promtool` accepts, mutual TLS and the plaintext-token rule, and the
//! defects an independent client written from the proto found (issue 16, section 5).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rand::Rng;
use sf_proto::pb;
use socialflow_e2e::grpc::{
    channel, exp, get, jobs, metric, progress, push_one, rt, submit, wait_final, SUCCEEDED,
};
use socialflow_e2e::{
    bin, free_port, http_get, scratch, socialflow_env, start_learner, start_learner_with,
    start_worker, tiny_job, wait_for, Proc, TOKEN, TWO_MAPS,
};
use tonic::Code;

const CANCELLED: i32 = pb::JobState::Cancelled as i32;
const FAILED: i32 = pb::JobState::Failed as i32;
const RUNNING: i32 = pb::JobState::Running as i32;

/// `promtool` from `$PROMTOOL` or the PATH. `tests/run.sh` sets `SOCIALFLOW_REQUIRE_PROMTOOL=1` (and fetches
/// Debian's prometheus package), so there a missing promtool fails instead of skipping.
fn promtool() -> Option<PathBuf> {
    let p = std::env::var_os("PROMTOOL")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("promtool"));
    let found = Command::new(&p)
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        found || std::env::var_os("SOCIALFLOW_REQUIRE_PROMTOOL").is_none(),
        "SOCIALFLOW_REQUIRE_PROMTOOL is set but {} does not run",
        p.display()
    );
    found.then_some(p)
}

/// The body of an HTTP response from `http_get` and its Content-Type.
fn body_and_type(resp: &str) -> (&str, String) {
    let (head, body) = resp.split_once("\r\n\r\n").expect("an HTTP response");
    let ctype = head
        .lines()
        .find_map(|l| {
            l.to_ascii_lowercase().strip_prefix("content-type:").map(|v| v.trim().to_string())
        })
        .unwrap_or_default();
    (body, ctype)
}

/// `promtool check metrics` on `body`: exits 0 and reports nothing.
fn promtool_clean(promtool: &Path, what: &str, body: &str) {
    let mut child = Command::new(promtool)
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("promtool");
    child.stdin.take().expect("stdin").write_all(body.as_bytes()).expect("feed promtool");
    let out = child.wait_with_output().expect("promtool output");
    let report =
        format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(
        out.status.success() && report.trim().is_empty(),
        "promtool check metrics on the {what}'s /metrics:\n{report}"
    );
}

#[test]
fn health_and_reflection_answer_without_a_token_and_metrics_pass_promtool() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let dir = scratch("probes");
    let l = start_learner(&dir, 64 << 20);
    let rt = rt();
    let ch = channel(&rt, &l.url);
    // grpc.health.v1 with no token at all, as a Kubernetes gRPC probe asks.
    let mut health = HealthClient::new(ch.clone());
    for service in ["", "socialflow.v1.JobService", "socialflow.v1.ExperienceService"] {
        let r = rt
            .block_on(health.check(HealthCheckRequest { service: service.into() }))
            .unwrap_or_else(|e| panic!("health of `{service}` without a token: {e:?}"));
        assert_eq!(r.into_inner().status, ServingStatus::Serving as i32, "`{service}`");
    }
    // Server reflection (what grpcurl list / describe use), also without a token.
    let mut refl = ServerReflectionClient::new(ch);
    let ask = |m: MessageRequest| ServerReflectionRequest {
        host: String::new(),
        message_request: Some(m),
    };
    let reqs = vec![
        ask(MessageRequest::ListServices(String::new())),
        ask(MessageRequest::FileContainingSymbol("socialflow.v1.JobService".into())),
    ];
    let mut answers = rt
        .block_on(refl.server_reflection_info(tokio_stream::iter(reqs)))
        .expect("reflection without a token")
        .into_inner();
    let mut next = || {
        rt.block_on(answers.message())
            .expect("a reflection reply")
            .expect("one more reply")
            .message_response
    };
    match next() {
        Some(MessageResponse::ListServicesResponse(l)) => {
            let names: Vec<&str> = l.service.iter().map(|s| s.name.as_str()).collect();
            for want in [
                "socialflow.v1.JobService",
                "socialflow.v1.ExperienceService",
                "grpc.health.v1.Health",
            ] {
                assert!(names.contains(&want), "reflection lists {names:?}, not {want}");
            }
        }
        other => panic!("list services answered {other:?}"),
    }
    match next() {
        Some(MessageResponse::FileDescriptorResponse(f)) => {
            assert!(!f.file_descriptor_proto.is_empty())
        }
        other => panic!("file containing socialflow.v1.JobService answered {other:?}"),
    }
    // The older v1alpha reflection, which some clients still ask for, lists the same services.
    {
        use tonic_reflection::pb::v1alpha::server_reflection_client::ServerReflectionClient as AlphaClient;
        use tonic_reflection::pb::v1alpha::server_reflection_request::MessageRequest as AlphaRequest;
        use tonic_reflection::pb::v1alpha::server_reflection_response::MessageResponse as AlphaResponse;
        use tonic_reflection::pb::v1alpha::ServerReflectionRequest as AlphaReflectionRequest;
        let mut alpha = AlphaClient::new(channel(&rt, &l.url));
        let req = AlphaReflectionRequest {
            host: String::new(),
            message_request: Some(AlphaRequest::ListServices(String::new())),
        };
        let mut replies = rt
            .block_on(alpha.server_reflection_info(tokio_stream::iter(vec![req])))
            .expect("v1alpha reflection without a token")
            .into_inner();
        match rt
            .block_on(replies.message())
            .expect("a v1alpha reply")
            .and_then(|r| r.message_response)
        {
            Some(AlphaResponse::ListServicesResponse(l)) => {
                let names: Vec<&str> = l.service.iter().map(|s| s.name.as_str()).collect();
                assert!(
                    names.contains(&"socialflow.v1.JobService"),
                    "v1alpha reflection lists {names:?}"
                );
            }
            other => panic!("v1alpha list services answered {other:?}"),
        }
    }
    // Everything else still needs the token.
    let mut anon = jobs(&rt, &l.url, None);
    assert_eq!(
        rt.block_on(anon.list_jobs(pb::ListJobsRequest {})).expect_err("no token").code(),
        Code::Unauthenticated
    );

    // Metrics of a learner with a job and of a worker that has run it, as promtool reads them.
    let worker_admin = format!("127.0.0.1:{}", free_port());
    let _w = Proc::spawn_logged(
        &bin("socialflow-worker"),
        &["--learner", &l.url, "--admin-addr", &worker_admin, "--max-backoff-s", "1"],
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        &dir.join("worker.log"),
    );
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let job = submit(&rt, &mut c, tiny_job(TWO_MAPS, "metrics", 100_000));
    wait_for("updates and worker inference", Duration::from_secs(300), || {
        let w = http_get(&worker_admin, "/metrics")?;
        (progress(&get(&rt, &mut c, job.job_id)).updates > 0
            && metric(&w, "socialflow_worker_inference_seconds_total") > 0.0)
            .then_some(())
    });
    let learner = http_get(&l.admin, "/metrics").expect("learner metrics");
    let worker = http_get(&worker_admin, "/metrics").expect("worker metrics");
    for (what, resp) in [("learner", &learner), ("worker", &worker)] {
        let (body, ctype) = body_and_type(resp);
        assert!(ctype.starts_with("text/plain; version=0.0.4"), "{what}: a client that does not ask for OpenMetrics gets the classic format, not {ctype}");
        assert!(!body.contains("# EOF") && !body.contains("nanoseconds"), "{what}");
        match promtool() {
            Some(p) => promtool_clean(&p, what, body),
            None => eprintln!("SKIPPED, promtool not found (tests/run.sh fetches it): its check of the {what}'s metrics"),
        }
    }
    rt.block_on(c.cancel_job(pb::CancelJobRequest { job_id: job.job_id })).expect("cancel");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A CA, a server certificate for localhost and a client certificate, all from rcgen (PEM).
struct Pki {
    ca: PathBuf,
    server: (PathBuf, PathBuf),
    client: (PathBuf, PathBuf),
    stranger: (PathBuf, PathBuf),
}

fn pki(dir: &Path) -> Pki {
    let write = |name: &str, text: String| {
        let p = dir.join(name);
        std::fs::write(&p, text).expect("pem");
        p
    };
    let ca_key = rcgen::KeyPair::generate().expect("key");
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).expect("params");
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    let ca_cert = ca_params.self_signed(&ca_key).expect("CA certificate");
    let issuer = rcgen::Issuer::from_params(&ca_params, &ca_key);
    let leaf = |tag: &str, names: Vec<String>| {
        let k = rcgen::KeyPair::generate().expect("key");
        let c = rcgen::CertificateParams::new(names)
            .expect("params")
            .signed_by(&k, &issuer)
            .expect("leaf certificate");
        (write(&format!("{tag}.pem"), c.pem()), write(&format!("{tag}.key"), k.serialize_pem()))
    };
    let server = leaf("server", vec!["localhost".into()]);
    let client = leaf("client", vec!["worker".into()]);
    // Signed by nobody the learner trusts.
    let sk = rcgen::generate_simple_self_signed(vec!["worker".to_string()]).expect("self-signed");
    let stranger = (
        write("stranger.pem", sk.cert.pem()),
        write("stranger.key", sk.signing_key.serialize_pem()),
    );
    Pki { ca: write("ca.pem", ca_cert.pem()), server, client, stranger }
}

#[test]
fn mutual_tls_admits_only_clients_with_a_certificate_from_its_ca() {
    let dir = scratch("mtls");
    let k = pki(&dir);
    let extra = format!(
        "tls_cert_file = \"{}\"\ntls_key_file = \"{}\"\ntls_client_ca_file = \"{}\"\n",
        k.server.0.display(),
        k.server.1.display(),
        k.ca.display()
    );
    let l = start_learner_with(&dir, 64 << 20, &extra);
    let port = l.url.rsplit(':').next().expect("port");
    let https = format!("https://localhost:{port}");
    let env = [("SOCIALFLOW_TOKEN", TOKEN)];
    let t = Duration::from_secs(60);
    let ca = k.ca.display().to_string();
    let (cert, key) = (k.client.0.display().to_string(), k.client.1.display().to_string());
    let (scert, skey) = (k.stranger.0.display().to_string(), k.stranger.1.display().to_string());
    let base = ["status", "--learner", &https, "--tls-ca-file", &ca];
    // No client certificate, or one from another CA: the handshake fails.
    let out = socialflow_env(&base, &env, t);
    assert!(!out.status.success(), "a client without a certificate was served");
    let out = socialflow_env(
        &[
            &base[..],
            &["--tls-client-cert-file", scert.as_str(), "--tls-client-key-file", skey.as_str()][..],
        ]
        .concat(),
        &env,
        t,
    );
    assert!(!out.status.success(), "a client with a certificate from another CA was served");
    // With its certificate: submit, and a worker with the same identity runs the job.
    let job = dir.join("job.toml");
    std::fs::write(&job, tiny_job(r#""merge""#, "over-mtls", 600)).expect("job");
    let ident = ["--tls-client-cert-file", cert.as_str(), "--tls-client-key-file", key.as_str()];
    let out = socialflow_env(
        &[
            &["submit", &job.display().to_string(), "--learner", &https, "--tls-ca-file", &ca][..],
            &ident[..],
        ]
        .concat(),
        &env,
        t,
    );
    assert!(
        out.status.success(),
        "submit over mutual TLS: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let _w = Proc::spawn_logged(
        &bin("socialflow-worker"),
        &[&["--learner", &https, "--tls-ca-file", &ca, "--max-backoff-s", "1"][..], &ident[..]]
            .concat(),
        &env,
        &dir.join("worker.log"),
    );
    wait_for("the job over mutual TLS to finish", Duration::from_secs(300), || {
        let out = socialflow_env(
            &[
                &["status", "1", "--json", "--learner", &https, "--tls-ca-file", &ca][..],
                &ident[..],
            ]
            .concat(),
            &env,
            t,
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).ok()?;
        (v["state"] == "succeeded").then_some(())
    });
    // A learner config naming a client CA without TLS is refused before any port is bound.
    let bad = dir.join("bad.toml");
    std::fs::write(
        &bad,
        format!(
            "scenarios_dir = \"configs/scenarios\"\ntls_client_ca_file = \"{}\"\n",
            k.ca.display()
        ),
    )
    .expect("config");
    let out = socialflow_env(&["learner", "--config", &bad.display().to_string()], &env, t);
    assert!(
        !out.status.success()
            && String::from_utf8_lossy(&out.stderr).contains("tls_client_ca_file"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// This machine's address on its default route, if it has one that is not loopback.
fn non_loopback_ip() -> Option<std::net::IpAddr> {
    let s = std::net::UdpSocket::bind("0.0.0.0:0").ok()?;
    s.connect("192.0.2.1:9").ok()?; // TEST-NET-1: no packet is sent by connect
    let ip = s.local_addr().ok()?.ip();
    (!ip.is_loopback() && !ip.is_unspecified()).then_some(ip)
}

#[test]
fn a_plaintext_token_from_off_loopback_is_refused_unless_allowed() {
    let Some(ip) = non_loopback_ip() else {
        eprintln!("no non-loopback address on this machine: the rule is covered by sf_service's unit tests only");
        return;
    };
    let dir = scratch("plaintext");
    for allow in [false, true] {
        let (g, a) = (free_port(), free_port());
        let d = dir.join(format!("allow-{allow}"));
        std::fs::create_dir_all(&d).expect("dir");
        let cfg = d.join("learner.toml");
        let text = format!(
            "grpc_addr = \"0.0.0.0:{g}\"\nadmin_addr = \"127.0.0.1:{a}\"\ndata_dir = \"{}\"\nscenarios_dir = \"configs/scenarios\"\nallow_plaintext_token = {allow}\n",
            d.join("data").display()
        );
        std::fs::write(&cfg, text).expect("config");
        let _p = Proc::spawn_logged(
            &bin("socialflow-learner"),
            &["--config", &cfg.display().to_string()],
            &[("SOCIALFLOW_TOKEN", TOKEN)],
            &d.join("learner.log"),
        );
        let env = [("SOCIALFLOW_TOKEN", TOKEN)];
        let remote = format!("http://{ip}:{g}");
        let out = wait_for("the learner on all interfaces", Duration::from_secs(60), || {
            let out =
                socialflow_env(&["status", "--learner", &remote], &env, Duration::from_secs(30));
            let err = String::from_utf8_lossy(&out.stderr).to_string();
            (out.status.success() || err.contains("plaintext") || err.contains("unauthenticated"))
                .then_some(out)
        });
        let err = String::from_utf8_lossy(&out.stderr);
        if allow {
            assert!(out.status.success(), "allowed, yet refused: {err}");
        } else {
            assert!(
                !out.status.success() && err.contains("plaintext"),
                "a token over plaintext from {ip} was accepted: {err}"
            );
            // From loopback the same learner serves.
            let local = socialflow_env(
                &["status", "--learner", &format!("http://127.0.0.1:{g}")],
                &env,
                Duration::from_secs(30),
            );
            assert!(local.status.success(), "{}", String::from_utf8_lossy(&local.stderr));
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn hostile_and_racing_clients_cannot_break_a_job() {
    let dir = scratch("hostile");
    let l = start_learner(&dir, 16 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));

    // Cancel right after submit on an idle learner: the job stays cancelled, never runs.
    for k in 0..8 {
        let j = submit(&rt, &mut c, tiny_job(TWO_MAPS, &format!("cancel-race-{k}"), 100_000));
        let r = rt
            .block_on(c.cancel_job(pb::CancelJobRequest { job_id: j.job_id }))
            .expect("cancel")
            .into_inner();
        assert_eq!(r.state, CANCELLED);
    }
    std::thread::sleep(Duration::from_secs(3));
    for j in rt.block_on(c.list_jobs(pb::ListJobsRequest {})).expect("list").into_inner().jobs {
        assert_eq!(
            j.state, CANCELLED,
            "job {} ({}) is {} after CancelJob answered CANCELLED",
            j.job_id, j.name, j.state
        );
    }

    // ListJobs carries summaries: big configs do not break a client with default limits.
    let padding = format!("# {}\n", "x".repeat(1_500_000));
    for k in 0..3 {
        let j = submit(
            &rt,
            &mut c,
            format!("{padding}{}", tiny_job(TWO_MAPS, &format!("big-{k}"), 100)),
        );
        rt.block_on(c.cancel_job(pb::CancelJobRequest { job_id: j.job_id })).expect("cancel");
    }
    let mut plain = pb::job_service_client::JobServiceClient::with_interceptor(
        channel(&rt, &l.url),
        sf_service::auth::AttachToken::new(Some(
            sf_service::auth::Token::new(TOKEN, "test").expect("token"),
        )),
    );
    let listed = rt
        .block_on(plain.list_jobs(pb::ListJobsRequest {}))
        .expect("ListJobs within a default client's 4 MiB")
        .into_inner()
        .jobs;
    assert_eq!(listed.len(), 11);
    assert!(listed.iter().all(|j| j.config_toml.is_empty()), "ListJobs returns summaries");
    assert!(
        get(&rt, &mut c, listed[0].job_id).config_toml.len() > 1_500_000,
        "GetJob carries the config"
    );
    let out = socialflow_env(
        &["status", "--learner", &l.url],
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        Duration::from_secs(30),
    );
    assert!(out.status.success(), "socialflow status: {}", String::from_utf8_lossy(&out.stderr));

    // A running job, then malformed batches from a token holder.
    let job = submit(&rt, &mut c, tiny_job(TWO_MAPS, "target", 1200));
    let mut e = exp(&rt, &l.url);
    let wid = rt
        .block_on(e.register(pb::RegisterRequest { name: "hostile".into(), ..Default::default() }))
        .expect("register")
        .into_inner()
        .worker_id;
    let a = wait_for("an assignment", Duration::from_secs(120), || {
        let r = rt
            .block_on(e.get_assignment(pb::GetAssignmentRequest { worker_id: wid }))
            .ok()?
            .into_inner();
        r.assignment.filter(|a| a.job_id == job.job_id)
    });
    let (obs_len, act) = (a.obs_len as usize, a.action_dim as usize);
    let empty = sf_proto::batch_to_wire(&sf_job::TransitionBatch::new(
        job.job_id.into(),
        wid.into(),
        obs_len,
        act,
    ));
    let st = push_one(&rt, &mut e, empty);
    assert_eq!(st.code(), Code::InvalidArgument, "an empty batch: {st:?}");
    let mut rng = rand::rng();
    let mut random = sf_job::TransitionBatch::new(job.job_id.into(), wid.into(), obs_len, act);
    for _ in 0..16 {
        let o: Vec<f32> = (0..obs_len).map(|_| rng.random_range(-1.0..1.0)).collect();
        let n: Vec<f32> = (0..obs_len).map(|_| rng.random_range(-1.0..1.0)).collect();
        let acts: Vec<f32> = (0..act).map(|_| rng.random_range(-1.0..1.0)).collect();
        random.push(&o, &acts, 0.0, &n, false, 0);
    }
    random.acted_by = sf_proto::acted_by_from_wire(a.policy_version);
    let st = push_one(&rt, &mut e, sf_proto::batch_to_wire(&random));
    assert_eq!(st.code(), Code::InvalidArgument, "random observations of the right shape: {st:?}");
    assert!(st.message().contains("mask") || st.message().contains("seg_id"), "{}", st.message());
    // Transitions summed over more steps than the job's sac.n_step (1 here) are refused by name.
    let mut spans = random.clone();
    spans.steps[0] = 2;
    let st = push_one(&rt, &mut e, sf_proto::batch_to_wire(&spans));
    assert_eq!(st.code(), Code::InvalidArgument, "a 2-step transition for a 1-step job: {st:?}");
    assert!(st.message().contains("sac.n_step"), "{}", st.message());
    std::thread::sleep(Duration::from_secs(1));
    assert_eq!(get(&rt, &mut c, job.job_id).state, RUNNING, "the job survives a hostile batch");
    let _w: Vec<Proc> = (0..2).map(|k| start_worker(&l, &dir, k)).collect();
    let done = wait_final(&rt, &mut c, job.job_id, "the job to finish after the hostile batches");
    assert_eq!(done.state, SUCCEEDED, "{}", done.message);

    // A job that fails mid-training (its artifact directory becomes a file): the failure names
    // its cause, and workers move on to the next job within seconds.
    let doomed = submit(&rt, &mut c, tiny_job(TWO_MAPS, "doomed", 1_000_000));
    let next = submit(&rt, &mut c, tiny_job(TWO_MAPS, "next", 400));
    wait_for("the doomed job to train", Duration::from_secs(300), || {
        (progress(&get(&rt, &mut c, doomed.job_id)).updates > 20).then_some(())
    });
    let art = PathBuf::from(get(&rt, &mut c, doomed.job_id).artifact_dir);
    // Renamed away at once (removing it races with the checkpoints the learner writes into it).
    let gone = art.with_extension("gone");
    std::fs::rename(&art, &gone).expect("move the artifact dir away");
    std::fs::write(&art, b"not a directory").expect("a file in its place");
    let _ = std::fs::remove_dir_all(&gone);
    let failed = wait_for("the doomed job to fail", Duration::from_secs(120), || {
        Some(get(&rt, &mut c, doomed.job_id)).filter(|j| j.state == FAILED)
    });
    assert!(
        !failed.message.is_empty() && !failed.message.contains("panicked"),
        "failure message: {}",
        failed.message
    );
    let t = Instant::now();
    wait_for("workers to move on to the next job", Duration::from_secs(30), || {
        (progress(&get(&rt, &mut c, next.job_id)).env_steps > 0).then_some(())
    });
    eprintln!("workers took {:.1} s to move on after the failure", t.elapsed().as_secs_f64());
    let done = wait_final(&rt, &mut c, next.job_id, "the next job");
    assert_eq!(done.state, SUCCEEDED, "{}", done.message);
    let _ = std::fs::remove_file(&art);
    let _ = std::fs::remove_dir_all(&dir);
}
