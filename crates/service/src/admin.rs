//! The admin HTTP server: `/metrics`, `/healthz` (liveness: the process serves HTTP) and
//! `/readyz` (readiness: the component says it can do work).
//!
//! `/metrics` answers in OpenMetrics to clients that ask for it (Prometheus does) and in the
//! classic Prometheus text format (0.0.4) to everything else (`curl`, `promtool check metrics`):
//! there a counter's HELP and TYPE lines name the sample (`..._total`), and `# EOF` goes.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::Context;
use axum::http::{header, StatusCode};
use axum::response::IntoResponse;
use axum::routing::get;
use axum::Router;
use prometheus_client::registry::Registry;

#[derive(Clone)]
struct AdminState {
    registry: Arc<Registry>,
    ready: Arc<AtomicBool>,
    refresh: Arc<dyn Fn() + Send + Sync>,
}

const OPENMETRICS: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";
const CLASSIC: &str = "text/plain; version=0.0.4; charset=utf-8";

async fn metrics(
    axum::extract::State(s): axum::extract::State<AdminState>,
    headers: axum::http::HeaderMap,
) -> impl IntoResponse {
    (s.refresh)();
    let mut out = String::new();
    if let Err(e) = prometheus_client::encoding::text::encode(&mut out, &s.registry) {
        return (StatusCode::INTERNAL_SERVER_ERROR, format!("encoding metrics: {e}"))
            .into_response();
    }
    let wants_openmetrics = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|a| a.contains("application/openmetrics-text"));
    if wants_openmetrics {
        (StatusCode::OK, [(header::CONTENT_TYPE, OPENMETRICS)], out).into_response()
    } else {
        (StatusCode::OK, [(header::CONTENT_TYPE, CLASSIC)], classic_text(&out)).into_response()
    }
}

/// OpenMetrics text as the classic Prometheus text format: counter families are named by
/// their `_total` sample in HELP and TYPE, UNIT lines and `# EOF` are dropped.
pub fn classic_text(openmetrics: &str) -> String {
    let counters: std::collections::HashSet<&str> = openmetrics
        .lines()
        .filter_map(|l| l.strip_prefix("# TYPE "))
        .filter_map(|l| l.strip_suffix(" counter"))
        .collect();
    let mut out = String::with_capacity(openmetrics.len());
    for line in openmetrics.lines() {
        if line == "# EOF" || line.starts_with("# UNIT ") {
            continue;
        }
        let meta = line
            .strip_prefix("# HELP ")
            .map(|r| ("# HELP ", r))
            .or_else(|| line.strip_prefix("# TYPE ").map(|r| ("# TYPE ", r)));
        match meta {
            Some((kind, rest)) => {
                let (name, tail) = rest.split_once(' ').unwrap_or((rest, ""));
                let name = if counters.contains(name) {
                    format!("{name}_total")
                } else {
                    name.to_string()
                };
                out.push_str(kind);
                out.push_str(&name);
                if !tail.is_empty() {
                    out.push(' ');
                    out.push_str(tail);
                }
            }
            None => out.push_str(line),
        }
        out.push('\n');
    }
    out
}

async fn ready(axum::extract::State(s): axum::extract::State<AdminState>) -> impl IntoResponse {
    if s.ready.load(Ordering::Acquire) {
        (StatusCode::OK, "ready\n")
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "not ready\n")
    }
}

/// Binds `addr` now (so a busy port fails before anything starts) and serves in the background.
/// Returns the bound address.
pub async fn serve(
    addr: SocketAddr,
    registry: Arc<Registry>,
    ready_flag: Arc<AtomicBool>,
    refresh: Arc<dyn Fn() + Send + Sync>,
) -> anyhow::Result<SocketAddr> {
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("binding admin port {addr}"))?;
    let bound = listener.local_addr().context("admin listener address")?;
    let app = Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(ready))
        .with_state(AdminState { registry, ready: ready_flag, refresh });
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!(error = %e, "admin server stopped");
        }
    });
    Ok(bound)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classic_text_names_counters_by_their_samples() {
        let om = "# HELP a_rpcs RPCs.\n# TYPE a_rpcs counter\na_rpcs_total{code=\"ok\"} 3\n# HELP a_bytes Bytes.\n# TYPE a_bytes gauge\n# UNIT a_bytes bytes\na_bytes 7\n# EOF\n";
        let c = classic_text(om);
        assert_eq!(c, "# HELP a_rpcs_total RPCs.\n# TYPE a_rpcs_total counter\na_rpcs_total{code=\"ok\"} 3\n# HELP a_bytes Bytes.\n# TYPE a_bytes gauge\na_bytes 7\n");
    }
}
