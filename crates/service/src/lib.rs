//! Service plumbing shared by the learner and the worker.
//!
//! Owns: the one table from domain errors to gRPC status codes ([`error`]), bearer-token auth
//! on both ends ([`auth`]), the clients' learner connection flags ([`conn`]) and the typed job
//! client ([`client`]), the admin HTTP server with Prometheus metrics, liveness and
//! readiness ([`admin`]), RPC counters and process gauges ([`metrics`]), bounded backoff
//! ([`backoff`]), logging set-up ([`logging`]), poison-tolerant locks ([`sync`]) and optional TLS
//! ([`tls`]). Must not: hold learner or worker logic.

pub mod admin;
pub mod auth;
pub mod backoff;
pub mod client;
pub mod conn;
pub mod error;
pub mod logging;
pub mod metrics;
pub mod signal;
pub mod sync;
pub mod tls;

pub use error::ServiceError;

/// Largest gRPC message either side accepts (a batch of 256 paper-size observations is ~7 MiB).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;
