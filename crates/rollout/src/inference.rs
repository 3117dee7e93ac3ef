//! Batched actor inference for rollouts: a policy version's actor and, for query-centric
//! observations, its segment table (computed once per version and reused every step).
//!
//! Owns: [`PolicyRunner`], what a worker (and evaluation) acts with. Must not: train.

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
        }
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
        let b = map_ids.len();
        let a = self.net.action_dim;
        assert_eq!(eps.len(), b * a, "one draw per action component");
        let eps = Tensor::<2>::from_data(TensorData::new(eps, [b, a]), &self.device);
        let (act, _) = self.actor.sample(&self.batch(rows, map_ids), self.table.as_ref(), eps);
        act.into_data().try_to_vec::<f32>().expect("actions are f32")
    }

    /// Deterministic actions (evaluation).
    pub fn mean(&self, rows: &[f32], map_ids: &[u32]) -> Vec<f32> {
        self.mean_of(&self.batch(rows, map_ids))
    }

    /// The standard deviation `[B * A]` (row-major) of the Gaussian each row's action is
    /// sampled from before its tanh: how much noise the policy samples with.
    pub fn std_dev(&self, rows: &[f32], map_ids: &[u32]) -> Vec<f32> {
        let (_, log_std) = self.actor.dist(&self.batch(rows, map_ids), self.table.as_ref());
        log_std.exp().into_data().try_to_vec::<f32>().expect("log-std is f32")
    }
}
