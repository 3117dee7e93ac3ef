//! Batched actor inference for rollouts: a policy version's actor and, for query-centric
//! observations, its segment table (computed once per version and reused every step).
//!
//! Owns: [`PolicyRunner`], what a worker (and evaluation) acts with, and how many rows one
//! inference call takes: all of a step's rows at once (training workers), or fixed-width
//! chunks padded to the same width ([`PolicyRunner::with_fixed_width`], evaluation), because
//! a row's action bits depend on how many rows the call holds (the CPU backend's matrix
//! products block by row count) and on nothing else. Must not: train.

use burn::tensor::{Device, Tensor, TensorData};
use sf_job::PolicyVersion;
use sf_nn::encoder::{SegmentInput, SegmentTable};
use sf_nn::{weights, Actor, Histories, NetConfig, ObsBatch};
use sf_sim::obs::{MapSegments, ObsSpec};
use sf_sim::Layout;

pub struct PolicyRunner {
    pub version: PolicyVersion,
    actor: Actor,
    table: Option<SegmentTable>,
    offsets: Vec<u32>,
    net: NetConfig,
    spec: ObsSpec,
    frame_dt_s: f32,
    device: Device,
    /// Rows per inference call, padded with copies of the last row; `None`: one call per step.
    fixed_rows: Option<usize>,
}

impl PolicyRunner {
    /// Loads actor weights (`sf_nn::weights` bytes) for `net` and encodes the maps' segments.
    pub fn from_bytes(
        net: &NetConfig,
        spec: &ObsSpec,
        frame_dt_s: f32,
        maps: &[&MapSegments],
        bytes: &[u8],
        version: PolicyVersion,
        device: &Device,
    ) -> Result<Self, weights::WeightsError> {
        let actor = weights::from_bytes(Actor::new(net, 0, device), bytes)?;
        Ok(Self::new(actor, net, spec, frame_dt_s, maps, version, device))
    }

    pub fn new(
        actor: Actor,
        net: &NetConfig,
        spec: &ObsSpec,
        frame_dt_s: f32,
        maps: &[&MapSegments],
        version: PolicyVersion,
        device: &Device,
    ) -> Self {
        let (table, offsets) = if spec.layout == Layout::QueryCentric {
            let input = SegmentInput::new(maps, device);
            let offsets = input.offsets.clone();
            (Some(actor.enc.segment_table(&input)), offsets)
        } else {
            (None, Vec::new())
        };
        Self {
            version,
            actor,
            table,
            offsets,
            net: net.clone(),
            spec: spec.clone(),
            frame_dt_s,
            device: device.clone(),
            fixed_rows: None,
        }
    }

    /// Runs every inference in calls of exactly `rows` rows (the last one padded with copies of
    /// its last row, whose actions are dropped), so a row's actions are the same bits whatever
    /// the number of rows stepped beside it: an evaluated episode's outcome then does not
    /// depend on how many simulators step together. `rows` is clamped to at least 1.
    pub fn with_fixed_width(mut self, rows: usize) -> Self {
        self.fixed_rows = Some(rows.max(1));
        self
    }

    /// `f` over `rows` (one observation per `map_ids` entry) and `extra`, the same number of
    /// floats per row (the sampled actions' normal draws; empty if none), returning the same
    /// number of floats per row: in one call, or in fixed-width padded chunks whose padding
    /// rows' outputs are dropped.
    fn chunked(
        &self,
        rows: &[f32],
        map_ids: &[u32],
        extra: &[f32],
        f: impl Fn(&[f32], &[u32], &[f32]) -> Vec<f32>,
    ) -> Vec<f32> {
        let n = map_ids.len();
        let width = match self.fixed_rows {
            Some(w) if n > 0 => w,
            _ => return f(rows, map_ids, extra),
        };
        let obs = rows.len() / n;
        let ext = extra.len() / n;
        let mut out = Vec::new();
        let (mut r, mut m, mut e) = (Vec::new(), Vec::new(), Vec::new());
        for start in (0..n).step_by(width) {
            let end = (start + width).min(n);
            r.clear();
            m.clear();
            e.clear();
            r.extend_from_slice(&rows[start * obs..end * obs]);
            m.extend_from_slice(&map_ids[start..end]);
            e.extend_from_slice(&extra[start * ext..end * ext]);
            for _ in end..start + width {
                r.extend_from_slice(&rows[(end - 1) * obs..end * obs]);
                m.push(map_ids[end - 1]);
                e.extend_from_slice(&extra[(end - 1) * ext..end * ext]);
            }
            let a = f(&r, &m, &e);
            let per_row = a.len() / width;
            out.extend_from_slice(&a[..(end - start) * per_row]);
        }
        out
    }

    /// Its actor's deterministic action as an ONNX model (`sf_nn::onnx`), the segment table of
    /// its maps included as constants (query-centric).
    pub fn export_onnx(
        &self,
        producer_version: &str,
        doc: &str,
    ) -> Result<Vec<u8>, sf_nn::onnx::OnnxError> {
        let x = sf_nn::onnx::ExportSpec {
            spec: &self.spec,
            net: &self.net,
            frame_dt_s: self.frame_dt_s,
            table: self.table.as_ref(),
            producer_version,
            doc,
        };
        sf_nn::onnx::export_actor(&self.actor, &x)
    }

    /// The network it runs (its action kind and size among them).
    pub fn net(&self) -> &NetConfig {
        &self.net
    }

    /// Rows of one step: in the query-centric layout each agent's history is encoded once for
    /// all its observers ([`Histories::Shared`]).
    pub fn batch(&self, rows: &[f32], map_ids: &[u32]) -> ObsBatch {
        ObsBatch::from_rows(
            rows,
            &self.spec,
            &self.net,
            self.frame_dt_s,
            map_ids,
            &self.offsets,
            self.histories(),
            &self.device,
        )
    }

    fn histories(&self) -> Histories {
        if self.spec.layout == Layout::QueryCentric {
            Histories::Shared
        } else {
            Histories::PerObservation
        }
    }

    /// The same step without sharing (benchmarks and tests compare the two).
    pub fn batch_unshared(&self, rows: &[f32], map_ids: &[u32]) -> ObsBatch {
        ObsBatch::from_rows(
            rows,
            &self.spec,
            &self.net,
            self.frame_dt_s,
            map_ids,
            &self.offsets,
            Histories::PerObservation,
            &self.device,
        )
    }

    /// Mean actions of a prepared batch.
    pub fn mean_of(&self, batch: &ObsBatch) -> Vec<f32> {
        self.actor
            .act_mean(batch, self.table.as_ref())
            .into_data()
            .try_to_vec::<f32>()
            .expect("actions are f32")
    }

    /// Stochastic actions `[B * A]` (row-major) for `B` observation rows, with the standard
    /// normal draws `eps` (`[B * A]`, row-major) taken by the caller (`drive`: from one stream
    /// or per episode).
    pub fn sample_with(&self, rows: &[f32], map_ids: &[u32], eps: Vec<f32>) -> Vec<f32> {
        let a = self.net.action_dim;
        assert_eq!(eps.len(), map_ids.len() * a, "one draw per action component");
        self.chunked(rows, map_ids, &eps, |rows, map_ids, eps| {
            let b = map_ids.len();
            let eps = Tensor::<2>::from_data(TensorData::new(eps.to_vec(), [b, a]), &self.device);
            let (act, _) = self.actor.sample(&self.batch(rows, map_ids), self.table.as_ref(), eps);
            act.into_data().try_to_vec::<f32>().expect("actions are f32")
        })
    }

    /// Deterministic actions (evaluation).
    pub fn mean(&self, rows: &[f32], map_ids: &[u32]) -> Vec<f32> {
        self.chunked(rows, map_ids, &[], |rows, map_ids, _| {
            self.mean_of(&self.batch(rows, map_ids))
        })
    }

    /// The standard deviation `[B * A]` (row-major) of the Gaussian each row's action is
    /// sampled from before its tanh: how much noise the policy samples with.
    pub fn std_dev(&self, rows: &[f32], map_ids: &[u32]) -> Vec<f32> {
        self.chunked(rows, map_ids, &[], |rows, map_ids, _| {
            let (_, log_std) = self.actor.dist(&self.batch(rows, map_ids), self.table.as_ref());
            log_std.exp().into_data().try_to_vec::<f32>().expect("log-std is f32")
        })
    }
}
