//! Metrics both services export: RPC counts by method and code, process memory.
//!
//! Names follow `socialflow_<component>_<what>_<unit>`; counters get `_total` from the
//! encoder; every metric has help text.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RpcLabels {
    pub method: String,
    pub code: String,
}

/// RPC outcome counters and the resident-memory gauge of one component.
#[derive(Clone)]
pub struct CommonMetrics {
    pub rpcs: Family<RpcLabels, Counter>,
    pub resident_memory_bytes: Gauge,
}

impl CommonMetrics {
    /// Registers under `socialflow_<component>_...`.
    pub fn register(reg: &mut Registry, component: &str) -> Self {
        let m = Self { rpcs: Family::default(), resident_memory_bytes: Gauge::default() };
        reg.register(
            format!("socialflow_{component}_rpcs"),
            "RPCs handled (server) or made (client), by method and gRPC status code",
            m.rpcs.clone(),
        );
        reg.register(
            format!("socialflow_{component}_resident_memory_bytes"),
            "Resident set size of the process",
            m.resident_memory_bytes.clone(),
        );
        m
    }

    /// Counts one RPC outcome.
    pub fn rpc(&self, method: &str, code: tonic::Code) {
        self.rpcs
            .get_or_create(&RpcLabels {
                method: method.to_string(),
                code: crate::error::code_label(code).to_string(),
            })
            .inc();
    }

    /// Reads the resident set size from /proc (Linux); leaves the gauge alone elsewhere.
    pub fn refresh(&self) {
        if let Some(b) = resident_bytes() {
            self.resident_memory_bytes.set(b as i64);
        }
    }
}

/// Resident set size of this process in bytes, from `/proc/self/statm`.
pub fn resident_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = s.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}
