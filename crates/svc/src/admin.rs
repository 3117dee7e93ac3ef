//! The admin HTTP server: `/metrics` (Prometheus/OpenMetrics text), `/healthz` (liveness:
//! the process serves HTTP) and `/readyz` (readiness: the component says it can do work).

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

async fn metrics(axum::extract::State(s): axum::extract::State<AdminState>) -> impl IntoResponse {
    (s.refresh)();
    let mut out = String::new();
    match prometheus_client::encoding::text::encode(&mut out, &s.registry) {
        Ok(()) => (StatusCode::OK, [(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], out).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("encoding metrics: {e}")).into_response(),
    }
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
pub async fn serve(addr: SocketAddr, registry: Arc<Registry>, ready_flag: Arc<AtomicBool>, refresh: Arc<dyn Fn() + Send + Sync>) -> anyhow::Result<SocketAddr> {
    let listener = tokio::net::TcpListener::bind(addr).await.with_context(|| format!("binding admin port {addr}"))?;
    let bound = listener.local_addr().context("admin listener address")?;
    let app = Router::new().route("/metrics", get(metrics)).route("/healthz", get(|| async { "ok\n" })).route("/readyz", get(ready)).with_state(AdminState { registry, ready: ready_flag, refresh });
    tokio::spawn(async move {
        if let Err(e) = axum::serve(listener, app).await {
            tracing::error!(error = %e, "admin server stopped");
        }
    });
    Ok(bound)
}
