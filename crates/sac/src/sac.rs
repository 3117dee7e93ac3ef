//! Soft Actor-Critic: configuration, state and the update, which reads top to bottom from
//! [`Sac::update`] through its numbered steps (`td_target`, `critic_step`, `actor_step`; compare
//! CleanRL's `sac_continuous_action.py`).
//!
//! Owns: the actor, the twin critic and its Polyak target, log-alpha, their Adam optimizers,
//! the update counter and the noise RNG. Must not: do IO on the update path (checkpoints are
//! written by `checkpoint` between updates). Target networks are plain (no autodiff) copies
//! moved only by Polyak averaging.

use burn::module::{Module, Param};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use sf_nn::device;
use sf_nn::encoder::{SegmentInput, SegmentTable};
use sf_nn::{Actor, Critic, Histories, NetConfig, ObsBatch};
use sf_sim::obs::{MapSegments, ObsSpec};

use crate::ops::column;
use crate::replay::Batch;

/// The update's tensor helpers, also under this module's path.
pub use crate::ops::{awac_weights, huber, polyak};

/// The `[sac]` section of a job config is the SAC config (one struct, one default: the
/// paper's table).
pub use sf_job::config::{BcTarget, CriticLoss, SacConfig};

/// What the critic step leaves for the actor step: the batch's observations and replayed
/// actions on the autodiff device, the critic's features without gradients (when reused or
/// shared), and the step's numbers.
struct CriticStep {
    obs: ObsBatch,
    act: Tensor<2>,
    features: Option<Tensor<2>>,
    q_mean: f32,
    loss: f32,
}

/// The actor step's numbers (zeros while the critic alone is trained).
#[derive(Default)]
struct ActorLosses {
    actor: f32,
    alpha_loss: f32,
    entropy: f32,
}

/// The policy's distribution on a batch and its reparameterised sample.
struct Sampled {
    mean: Tensor<2>,
    log_std: Tensor<2>,
    a_new: Tensor<2>,
    logp: Tensor<2>,
}

/// `log(alpha)` as a module so Adam can optimise it.
#[derive(Module, Debug)]
pub struct LogAlpha {
    pub value: Param<Tensor<1>>,
}

/// What one update reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Losses {
    pub critic: f32,
    pub actor: f32,
    pub alpha_loss: f32,
    pub alpha: f32,
    /// Mean of -log pi(a|s) over the batch.
    pub entropy: f32,
    pub q_mean: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum SacError {
    #[error("sac config: {0}")]
    Net(#[from] sf_nn::config::NetConfigError),
    #[error("sac config: gamma, tau in (0, 1], batch_size and initial_alpha positive; got {0:?}")]
    Settings(Box<SacConfig>),
    #[error(transparent)]
    Device(#[from] device::DeviceError),
}

/// The learner's SAC state.
pub struct Sac {
    pub cfg: SacConfig,
    pub net: NetConfig,
    pub spec: ObsSpec,
    pub frame_dt_s: f32,
    pub plain: Device,
    pub ad: Device,
    pub actor: Actor,
    pub critic: Critic,
    pub target: Critic,
    /// `sac.actor_average_tau`: the Polyak average of the actor (inference copy).
    pub actor_avg: Option<Actor>,
    pub log_alpha: LogAlpha,
    pub(crate) opt_actor: burn::optim::ModuleOptimizer,
    pub(crate) opt_critic: burn::optim::ModuleOptimizer,
    pub(crate) opt_alpha: burn::optim::ModuleOptimizer,
    /// Query-centric: every map's segments on each device.
    pub(crate) seg_plain: Option<SegmentInput>,
    pub(crate) seg_ad: Option<SegmentInput>,
    pub updates: u64,
    pub(crate) rng: ChaCha8Rng,
}

impl Sac {
    /// `maps` are the maps whose segments query-centric observations index (by map id).
    pub fn new(
        cfg: SacConfig,
        net: NetConfig,
        spec: ObsSpec,
        frame_dt_s: f32,
        maps: &[&MapSegments],
    ) -> Result<Self, SacError> {
        net.validate()?;
        if !(cfg.gamma > 0.0
            && cfg.gamma <= 1.0
            && cfg.tau > 0.0
            && cfg.tau <= 1.0
            && cfg.batch_size > 0
            && cfg.initial_alpha > 0.0)
        {
            return Err(SacError::Settings(Box::new(cfg)));
        }
        let plain = device::device(device_kind(cfg.device))?;
        let ad = plain.clone().autodiff();
        let mut actor = Actor::new(&net, cfg.seed.wrapping_mul(3).wrapping_add(1), &ad);
        let critic = Critic::new(&net, cfg.seed.wrapping_mul(3).wrapping_add(2), &ad);
        if cfg.shared_encoder {
            actor.enc = critic.enc.clone();
        }
        let target = critic.valid();
        let actor_avg = cfg.actor_average_tau.map(|_| actor.valid());
        let la = Tensor::from_data(TensorData::new(vec![cfg.initial_alpha.ln()], [1]), &ad);
        let qc = spec.layout == sf_sim::Layout::QueryCentric;
        Ok(Self {
            seg_plain: qc.then(|| SegmentInput::new(maps, &plain)),
            seg_ad: qc.then(|| SegmentInput::new(maps, &ad)),
            opt_actor: AdamConfig::new().init(),
            opt_critic: AdamConfig::new().init(),
            opt_alpha: AdamConfig::new().init(),
            log_alpha: LogAlpha { value: Param::from_tensor(la) },
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            net,
            spec,
            frame_dt_s,
            plain,
            ad,
            actor,
            critic,
            target,
            actor_avg,
            updates: 0,
        })
    }

    pub(crate) fn batch_on(&self, rows: &[f32], map_ids: &[u32], device: &Device) -> ObsBatch {
        let offsets = self.seg_plain.as_ref().map_or(&[][..], |s| &s.offsets[..]);
        ObsBatch::from_rows(
            rows,
            &self.spec,
            &self.net,
            self.frame_dt_s,
            map_ids,
            offsets,
            Histories::PerObservation,
            device,
        )
    }

    fn noise(&mut self, b: usize, device: &Device) -> Tensor<2> {
        let a = self.net.action_dim;
        let v: Vec<f32> = (0..b * a).map(|_| self.rng.sample(StandardNormal)).collect();
        Tensor::from_data(TensorData::new(v, [b, a]), device)
    }

    pub fn alpha(&self) -> f32 {
        self.log_alpha.value.val().exp().into_scalar::<f32>()
    }

    /// One SAC update on a sampled batch: the TD target, one critic step, one actor and
    /// temperature step (none while the critic alone is trained), the Polyak moves.
    pub fn update(&mut self, batch: &Batch) -> Losses {
        let alpha = self.alpha();
        let y = self.td_target(batch, alpha);
        let c = self.critic_step(batch, y);
        let (critic, q_mean) = (c.loss, c.q_mean);
        // Not while the critic alone is trained (`critic_pretrain_updates`).
        let cloning = self.updates < self.cfg.bc_updates;
        let evaluating_only =
            !cloning && self.updates < self.cfg.bc_updates + self.cfg.critic_pretrain_updates;
        let a = if evaluating_only {
            ActorLosses::default()
        } else {
            self.actor_step(batch, c, alpha, cloning)
        };

        // 5. Polyak: target <- (1 - tau) target + tau critic.
        self.target = polyak(self.target.clone(), &self.critic.valid(), self.cfg.tau);
        if let (Some(avg), Some(t)) = (self.actor_avg.take(), self.cfg.actor_average_tau) {
            self.actor_avg = Some(polyak(avg, &self.actor.valid(), t));
        }
        self.updates += 1;
        Losses {
            critic,
            actor: a.actor,
            alpha_loss: a.alpha_loss,
            alpha: self.alpha(),
            entropy: a.entropy,
            q_mean,
        }
    }

    /// 1. The TD target without gradients, on the autodiff device:
    ///    y = s r + gamma^n (1 - d) (min Q'(s', a') - alpha log pi(a'|s')), n the decision steps
    ///    the row spans (its reward already summed over them).
    fn td_target(&mut self, batch: &Batch, alpha: f32) -> Tensor<2> {
        let next = self.batch_on(&batch.next_obs, &batch.map_ids, &self.plain);
        let actor_v = self.actor.valid();
        let table = self.seg_plain.as_ref().map(|s| actor_v.enc.segment_table(s));
        let plain = self.plain.clone();
        let eps = self.noise(batch.len(), &plain);
        let (a2, logp2) = actor_v.sample(&next, table.as_ref(), eps);
        let table = self.seg_plain.as_ref().map(|s| self.target.enc.segment_table(s));
        let (tq1, tq2) = self.target.forward(&next, table.as_ref(), a2);
        let soft_q = tq1.min_pair(tq2) - logp2.mul_scalar(alpha);
        let discount = column(&batch.bootstrap_discounts(self.cfg.gamma), &self.plain);
        let y = column(&batch.rewards, &self.plain).mul_scalar(self.cfg.reward_scale)
            + discount * soft_q;
        Tensor::<2>::from_data(y.into_data(), &self.ad)
    }

    /// 2. Critic: both heads' loss (MSE or Huber) to `y`, one Adam step; a shared encoder is
    ///    copied to the actor.
    fn critic_step(&mut self, batch: &Batch, y: Tensor<2>) -> CriticStep {
        let obs = self.batch_on(&batch.obs, &batch.map_ids, &self.ad);
        let table = self.seg_ad.as_ref().map(|s| self.critic.enc.segment_table(s));
        let act = Tensor::<2>::from_data(
            TensorData::new(batch.actions.clone(), [batch.len(), self.net.action_dim]),
            &self.ad,
        );
        let f_critic = self.critic.enc.forward(&obs, table.as_ref());
        let features = (self.cfg.reuse_critic_features || self.cfg.shared_encoder)
            .then(|| Tensor::<2>::from_data(f_critic.clone().into_data(), &self.ad));
        let (q1, q2) = self.critic.heads(f_critic.clone(), act.clone());
        // The conservative term (`cql_weight`) on the same features and replayed-action heads.
        let cql = (self.cfg.cql_weight > 0.0)
            .then(|| self.conservative_term(batch, f_critic, q1.clone(), q2.clone()));
        // Detached: a node on q1 that no backward consumes would stay in the autodiff graph and
        // slow every later critic-only update (`critic_pretrain_updates`), which has no actor
        // backward (`bench sac --phase critic`).
        let q_mean = q1.clone().detach().mean().into_scalar::<f32>();
        let loss_c = match self.cfg.critic_loss {
            CriticLoss::Mse => (q1 - y.clone()).square().mean() + (q2 - y).square().mean(),
            // 2 x Huber, so that it equals the squared error within delta of the target.
            CriticLoss::Huber => (huber(q1 - y.clone(), self.cfg.huber_delta)
                + huber(q2 - y, self.cfg.huber_delta))
            .mul_scalar(2.0),
        };
        let loss_c = match cql {
            Some(term) => loss_c + term.mul_scalar(self.cfg.cql_weight),
            None => loss_c,
        };
        let loss = loss_c.clone().into_scalar::<f32>();
        let grads = GradientsParams::from_grads(loss_c.backward(), &self.critic);
        self.critic = self.opt_critic.step(self.cfg.lr_critic, self.critic.clone(), grads);
        if self.cfg.shared_encoder {
            self.actor.enc = self.critic.enc.clone();
        }
        CriticStep { obs, act, features, q_mean, loss }
    }

    /// 2'. CQL(H)'s regulariser, summed over both heads: `logsumexp_a Q(s, a) - Q(s, a_replay)`
    ///    averaged over the batch, the log-sum-exp over `cql_samples` uniform actions in
    ///    `[-1, 1]^A` and as many samples of the current policy (off the graph) per state, each
    ///    minus its log-density, so that it estimates `log` of the integral of `exp Q` over the
    ///    action box. `f` are the critic's features of the batch (with gradients), `q1`, `q2`
    ///    its heads on the replayed actions.
    fn conservative_term(
        &mut self,
        batch: &Batch,
        f: Tensor<2>,
        q1: Tensor<2>,
        q2: Tensor<2>,
    ) -> Tensor<1> {
        let (b, a_dim, n) = (batch.len(), self.net.action_dim, self.cfg.cql_samples);
        let d = f.dims()[1];
        // Row i * n + j: state i's j-th sample.
        let rep =
            |t: Tensor<2>, w: usize| t.unsqueeze_dim::<3>(1).repeat_dim(1, n).reshape([b * n, w]);
        let actor_v = self.actor.valid();
        let obs = self.batch_on(&batch.obs, &batch.map_ids, &self.plain);
        let table = self.seg_plain.as_ref().map(|s| actor_v.enc.segment_table(s));
        let (mean, log_std) = actor_v.dist(&obs, table.as_ref());
        let plain = self.plain.clone();
        let eps = self.noise(b * n, &plain);
        let (a_pi, logp_pi) =
            sf_nn::policy::tanh_gaussian_sample(rep(mean, a_dim), rep(log_std, a_dim), eps);
        let a_pi = Tensor::<2>::from_data(a_pi.into_data(), &self.ad);
        let logp_pi = Tensor::<2>::from_data(logp_pi.into_data(), &self.ad).reshape([b, n]);
        let uniform: Vec<f32> =
            (0..b * n * a_dim).map(|_| self.rng.random_range(-1.0f32..1.0)).collect();
        let a_uni = Tensor::<2>::from_data(TensorData::new(uniform, [b * n, a_dim]), &self.ad);
        // The uniform density on the box is 2^-A.
        let log_uniform = -(a_dim as f32) * std::f32::consts::LN_2;
        let f_rep = rep(f, d);
        let (u1, u2) = self.critic.heads(f_rep.clone(), a_uni);
        let (p1, p2) = self.critic.heads(f_rep, a_pi);
        let head = |u: Tensor<2>, p: Tensor<2>, q_data: Tensor<2>| -> Tensor<1> {
            let x = Tensor::cat(
                vec![
                    u.reshape([b, n]).sub_scalar(log_uniform),
                    p.reshape([b, n]) - logp_pi.clone(),
                ],
                1,
            );
            let m = x.clone().detach().max_dim(1);
            let lse = (x - m.clone().repeat_dim(1, 2 * n)).exp().sum_dim(1).log() + m;
            // Minus log(2n): the log of the samples' mean, not their sum (a constant).
            lse.mean().sub_scalar((2.0 * n as f32).ln()) - q_data.mean()
        };
        head(u1, p1, q1) + head(u2, p2, q2)
    }

    /// 3. Actor: maximise min(Q1, Q2)(s, a~pi) - alpha log pi, critic features taken without
    ///    gradients (the cloning updates instead fit the replayed actions); 4. temperature.
    fn actor_step(
        &mut self,
        batch: &Batch,
        c: CriticStep,
        alpha: f32,
        cloning: bool,
    ) -> ActorLosses {
        let fc = match c.features {
            Some(f) => f,
            None => {
                let critic_v = self.critic.valid();
                let obs_plain = self.batch_on(&batch.obs, &batch.map_ids, &self.plain);
                let table = self.seg_plain.as_ref().map(|s| critic_v.enc.segment_table(s));
                Tensor::<2>::from_data(
                    critic_v.enc.forward(&obs_plain, table.as_ref()).into_data(),
                    &self.ad,
                )
            }
        };
        let ad = self.ad.clone();
        let eps = self.noise(batch.len(), &ad);
        let (mean, log_std) = if self.cfg.shared_encoder {
            self.actor.dist_from_features(fc.clone())
        } else {
            let table = self.seg_ad.as_ref().map(|s| self.actor.enc.segment_table(s));
            self.actor.dist(&c.obs, table.as_ref())
        };
        // Cloning trains the mean and log-std alone, so its sample (only the reported entropy
        // reads it) is drawn off the autodiff graph: nodes that no backward pass consumes stay
        // in burn's graph, which every later backward sweeps, and updates slowed with every
        // cloning update (2x after 1,000 of them on the L3 job, `bench sac --phase cloning`).
        let (mean_s, log_std_s) = if cloning {
            (mean.clone().detach(), log_std.clone().detach())
        } else {
            (mean.clone(), log_std.clone())
        };
        let (a_new, logp) = sf_nn::policy::tanh_gaussian_sample(mean_s, log_std_s, eps);
        let loss_a = if cloning {
            // 3'. Cloning updates (the first `bc_updates`): the replayed actions, or IDM's
            // recorded labels where the rows have them.
            if self.cfg.bc_target == BcTarget::Oracle {
                let (target, labelled) = self.oracle_target(batch);
                self.cloning_loss(mean, log_std, target, Some(labelled))
            } else {
                self.cloning_loss(mean, log_std, c.act, None)
            }
        } else {
            self.actor_objective(
                Sampled { mean, log_std, a_new, logp: logp.clone() },
                fc,
                c.act,
                batch,
                alpha,
            )
        };
        let actor = loss_a.clone().into_scalar::<f32>();
        let grads = GradientsParams::from_grads(loss_a.backward(), &self.actor);
        self.actor =
            self.opt_actor.step(self.cfg.actor_lr(self.updates), self.actor.clone(), grads);

        // 4. Temperature: push the policy's entropy towards the target (not while cloning).
        let target_entropy = self.cfg.target_entropy.unwrap_or(-(self.net.action_dim as f32));
        let logp = Tensor::<2>::from_data(logp.into_data(), &self.ad);
        let entropy = -logp.clone().mean().into_scalar::<f32>();
        // While cloning the temperature does not move: its loss is reported, off the graph.
        let log_alpha =
            if cloning { self.log_alpha.value.val().detach() } else { self.log_alpha.value.val() };
        let loss_al =
            (log_alpha.unsqueeze_dim::<2>(0) * logp.add_scalar(target_entropy)).mean().neg();
        let alpha_loss = loss_al.clone().into_scalar::<f32>();
        if !cloning {
            let grads = GradientsParams::from_grads(loss_al.backward(), &self.log_alpha);
            self.log_alpha = self.opt_alpha.step(self.cfg.lr_alpha, self.log_alpha.clone(), grads);
        }
        ActorLosses { actor, alpha_loss, entropy }
    }

    /// Behaviour cloning: the mean action to `target` (row weights `w_rows`, or all rows), the
    /// log-std to `bc_log_std`.
    fn cloning_loss(
        &self,
        mean: Tensor<2>,
        log_std: Tensor<2>,
        target: Tensor<2>,
        w_rows: Option<Tensor<2>>,
    ) -> Tensor<1> {
        let err = (mean.tanh() - target).square();
        let err = match w_rows {
            Some(w) => (err * w).mean(),
            None => err.mean(),
        };
        err + log_std.sub_scalar(self.cfg.bc_log_std(self.actor.log_std_min)).square().mean()
    }

    /// The batch's oracle labels as a cloning target (`[b, act_dim]`, rows without a label at
    /// 0) and a `[b, 1]` column of 1 for the rows that have one (all 0 for a batch without
    /// labels).
    fn oracle_target(&self, batch: &Batch) -> (Tensor<2>, Tensor<2>) {
        let (b, a_dim) = (batch.len(), self.net.action_dim);
        let mut labels = vec![0.0; b * a_dim];
        let mut labelled = vec![0.0; b];
        if batch.oracle.len() == b * a_dim {
            for (i, row) in batch.oracle.chunks_exact(a_dim).enumerate() {
                if row.iter().all(|x| x.is_finite()) {
                    labels[i * a_dim..(i + 1) * a_dim].copy_from_slice(row);
                    labelled[i] = 1.0;
                }
            }
        }
        (
            Tensor::<2>::from_data(TensorData::new(labels, [b, a_dim]), &self.ad),
            column(&labelled, &self.ad),
        )
    }

    /// 3. SAC's actor loss `alpha log pi - min Q`, plus the behaviour-cloning term while
    ///    `bc_weight` (constant, or fading over `bc_decay_updates`) is positive: towards the
    ///    replayed actions, the zero residual or IDM's recorded labels (`bc_target`), with
    ///    `bc_q_filter` only on the rows where the critic rates IDM's action at least as high
    ///    as the policy's (in every row for the components of `bc_hold_dims`, which with
    ///    `bc_hold_clone_only` get no gradient from Q), scaled by the batch's mean |Q|.
    fn actor_objective(
        &self,
        pi: Sampled,
        fc: Tensor<2>,
        act: Tensor<2>,
        batch: &Batch,
        alpha: f32,
    ) -> Tensor<1> {
        let critic_ng = self.critic.clone().no_grad();
        let (q1_pi, q2_pi) = critic_ng.heads(fc.clone(), self.detach_held(pi.a_new));
        let q_pi = q1_pi.min_pair(q2_pi);
        let since = self.updates - self.cfg.bc_updates - self.cfg.critic_pretrain_updates;
        let w = match self.cfg.bc_decay_updates {
            0 => self.cfg.bc_weight,
            d if since < d => self.cfg.bc_weight * (1.0 - since as f32 / d as f32),
            _ => 0.0,
        };
        let sac = (pi.logp.mul_scalar(alpha) - q_pi.clone()).mean();
        if w <= 0.0 {
            return sac;
        }
        // 3''. Behaviour-cloning term, constant or fading (offline-to-online hand-over).
        let q_scale = q_pi.clone().detach().abs().mean().into_scalar::<f32>().max(1.0);
        let term = match self.cfg.bc_target {
            BcTarget::Replay => {
                // AWAC-style: rows weighted by how much the critic prefers the replayed action.
                let rows = self.cfg.bc_awac_lambda.map(|lambda| {
                    let (q1_d, q2_d) = critic_ng.heads(fc, act.clone());
                    let w = awac_weights(q1_d.min_pair(q2_d), q_pi.clone().detach(), lambda);
                    Tensor::<2>::from_data(w.into_data(), &self.ad)
                });
                self.cloning_loss(pi.mean, pi.log_std, act, rows)
            }
            BcTarget::Zero | BcTarget::Oracle => {
                // IDM's action: zero for residual kinds, else the worker's recorded label
                // (rows without one left out).
                let (target, labelled) = if self.cfg.bc_target == BcTarget::Oracle {
                    let (t, l) = self.oracle_target(batch);
                    (t, Some(l))
                } else {
                    (Tensor::<2>::zeros(act.dims(), &self.ad), None)
                };
                let rows = if self.cfg.bc_q_filter {
                    let (q1_0, q2_0) = critic_ng.heads(fc, target.clone());
                    let q_idm = q1_0.min_pair(q2_0);
                    let keep = q_idm.greater_equal(q_pi.detach()).float();
                    let keep = self.hold_components(keep);
                    let keep = match labelled {
                        Some(l) => keep * l,
                        None => keep,
                    };
                    Some(Tensor::<2>::from_data(keep.into_data(), &self.ad))
                } else {
                    labelled
                };
                self.cloning_loss(pi.mean, pi.log_std, target, rows)
            }
        };
        sac + term.mul_scalar(w * q_scale)
    }

    /// The policy's sampled actions as the actor loss's critic sees them: with
    /// `bc_hold_clone_only`, the components of `bc_hold_dims` detached (same values, no
    /// gradient from Q), so only the cloning term and the entropy bonus train them; unchanged
    /// otherwise.
    fn detach_held(&self, a: Tensor<2>) -> Tensor<2> {
        if !self.cfg.bc_hold_clone_only || self.cfg.bc_hold_dims.is_empty() {
            return a;
        }
        let (hold, free) = self.hold_masks(a.dims()[0]);
        a.clone() * free + a.detach() * hold
    }

    /// `[b, act_dim]` masks: 1 in the columns of `bc_hold_dims` (held) and its complement
    /// (free).
    fn hold_masks(&self, b: usize) -> (Tensor<2>, Tensor<2>) {
        let a_dim = self.net.action_dim;
        let mut hold = vec![0.0f32; a_dim];
        for &k in &self.cfg.bc_hold_dims {
            hold[k] = 1.0;
        }
        let hold =
            Tensor::<2>::from_data(TensorData::new(hold, [1, a_dim]), &self.ad).repeat_dim(0, b);
        let free = hold.clone().neg().add_scalar(1.0);
        (hold, free)
    }

    /// The Q filter's `[b, 1]` keep column widened to `[b, act_dim]` with 1 in the columns of
    /// `bc_hold_dims` (cloned in every row); unchanged without them.
    fn hold_components(&self, keep: Tensor<2>) -> Tensor<2> {
        if self.cfg.bc_hold_dims.is_empty() {
            return keep;
        }
        let (hold, free) = self.hold_masks(keep.dims()[0]);
        keep.repeat_dim(1, self.net.action_dim) * free + hold
    }

    /// An inference copy of the actor and, for query-centric observations, its segment table
    /// (compute once per weight version; workers cache both).
    pub fn policy(&self) -> (Actor, Option<SegmentTable>) {
        let a = self.actor.valid();
        let t = self.seg_plain.as_ref().map(|s| a.enc.segment_table(s));
        (a, t)
    }

    /// The actor's weights (inference copy) as `sf_nn::weights` bytes: what workers load.
    pub fn actor_bytes(&self) -> Result<Vec<u8>, sf_nn::weights::WeightsError> {
        sf_nn::weights::to_bytes(&self.actor.valid())
    }

    /// The weights rollouts act with: the averaged actor with `sac.act_with_average`, else
    /// the actor itself.
    pub fn acting_actor_bytes(&self) -> Result<Vec<u8>, sf_nn::weights::WeightsError> {
        match &self.actor_avg {
            Some(avg) if self.cfg.act_with_average => sf_nn::weights::to_bytes(avg),
            _ => self.actor_bytes(),
        }
    }

    /// The weights a job's validation scores and its final policy takes: the averaged actor
    /// with `sac.actor_average_tau`, else the actor itself.
    pub fn selected_actor_bytes(&self) -> Result<Vec<u8>, sf_nn::weights::WeightsError> {
        match &self.actor_avg {
            Some(avg) => sf_nn::weights::to_bytes(avg),
            None => self.actor_bytes(),
        }
    }

    /// Builds an inference batch on the plain device.
    pub fn obs_batch(&self, rows: &[f32], map_ids: &[u32]) -> ObsBatch {
        self.batch_on(rows, map_ids, &self.plain)
    }
}

/// The backend a job's `sac.device` names.
pub fn device_kind(d: sf_job::config::Device) -> device::DeviceKind {
    use sf_job::config::Device as Job;
    match d {
        Job::Cpu => device::DeviceKind::Cpu,
        Job::Ndarray => device::DeviceKind::Ndarray,
        Job::Cuda => device::DeviceKind::Cuda,
        Job::Wgpu => device::DeviceKind::Wgpu,
    }
}
