//! The learner's gRPC handlers: `JobService` and `ExperienceService`.
//!
//! Owns: request decoding (through `sf_proto`), the calls into [`crate::Inner`] and the mapping
//! of results to responses; errors become statuses only through `sf_service::ServiceError`. What
//! the calls do lives beside `Inner`: jobs in `lib.rs`, a training job's worker calls in
//! `experience.rs`, an evaluation's in `eval.rs`.
//! Must not: block the runtime (store IO and ingest go through `spawn_blocking`) or run
//! tensor code.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use sf_proto::pb::experience_service_server::ExperienceService;
use sf_proto::pb::job_service_server::JobService;
use sf_proto::{pb, WireError};
use sf_service::ServiceError;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Code, Request, Response, Status, Streaming};

use crate::Inner;

type Res<T> = Result<Response<T>, Status>;
type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[derive(Clone)]
pub struct Jobs(pub Arc<Inner>);

#[derive(Clone)]
pub struct Experience(pub Arc<Inner>);

/// Counts the outcome and converts the error.
fn done<T>(inner: &Inner, method: &str, r: Result<T, ServiceError>) -> Res<T> {
    match r {
        Ok(v) => {
            inner.metrics.common.rpc(method, Code::Ok);
            Ok(Response::new(v))
        }
        Err(e) => {
            inner.metrics.common.rpc(method, e.code());
            Err(e.into())
        }
    }
}

#[tonic::async_trait]
impl JobService for Jobs {
    async fn submit_job(&self, req: Request<pb::SubmitJobRequest>) -> Res<pb::Job> {
        let r = self.0.submit(req.into_inner().config_toml).await;
        done(&self.0, "SubmitJob", r.map(|j| sf_proto::job_to_wire(&j)))
    }

    async fn get_job(&self, req: Request<pb::GetJobRequest>) -> Res<pb::Job> {
        let r = self.0.job(req.into_inner().job_id).await;
        done(&self.0, "GetJob", r.map(|j| sf_proto::job_to_wire(&j)))
    }

    async fn list_jobs(&self, _req: Request<pb::ListJobsRequest>) -> Res<pb::ListJobsResponse> {
        let r = self.0.jobs().await;
        // Summaries: configs can be megabytes each, and a list of them would outgrow a default
        // client's 4 MiB receive limit. GetJob carries the config.
        let summary = |j: &sf_job::JobRecord| pb::Job {
            config_toml: String::new(),
            ..sf_proto::job_to_wire(j)
        };
        done(
            &self.0,
            "ListJobs",
            r.map(|js| pb::ListJobsResponse { jobs: js.iter().rev().map(summary).collect() }),
        )
    }

    async fn cancel_job(&self, req: Request<pb::CancelJobRequest>) -> Res<pb::Job> {
        let r = self.0.cancel(req.into_inner().job_id).await;
        done(&self.0, "CancelJob", r.map(|j| sf_proto::job_to_wire(&j)))
    }

    async fn get_job_file(&self, req: Request<pb::GetJobFileRequest>) -> Res<pb::JobFile> {
        let pb::GetJobFileRequest { job_id, name } = req.into_inner();
        let r = self.0.job_file(job_id, &name).await;
        done(&self.0, "GetJobFile", r.map(|content| pb::JobFile { job_id, name, content }))
    }

    type WatchJobStream = BoxStream<pb::JobProgress>;

    async fn watch_job(&self, req: Request<pb::WatchJobRequest>) -> Res<Self::WatchJobStream> {
        let id = req.into_inner().job_id;
        let first = match self.0.job(id).await {
            Ok(j) => j,
            Err(e) => return done(&self.0, "WatchJob", Err(e)),
        };
        let (tx, rx) = mpsc::channel(4);
        let inner = Arc::clone(&self.0);
        tokio::spawn(async move {
            let mut last = None;
            let mut cur = first;
            loop {
                let msg = sf_proto::progress_to_wire(cur.id, cur.state, &cur.progress);
                if last.as_ref() != Some(&msg) {
                    if tx.send(Ok(msg)).await.is_err() {
                        return;
                    }
                    last = Some(msg);
                }
                if cur.state.is_final() {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(250)).await;
                cur = match inner.job(id).await {
                    Ok(j) => j,
                    Err(e) => {
                        let _ = tx.send(Err(e.into())).await;
                        return;
                    }
                };
            }
        });
        done(&self.0, "WatchJob", Ok(Box::pin(ReceiverStream::new(rx)) as Self::WatchJobStream))
    }
}

#[tonic::async_trait]
impl ExperienceService for Experience {
    async fn register(&self, req: Request<pb::RegisterRequest>) -> Res<pb::RegisterResponse> {
        let r = req.into_inner();
        let id = self.0.register_worker(&r.name, r.runs_idm_ego);
        done(
            &self.0,
            "Register",
            Ok(pb::RegisterResponse { worker_id: id, heartbeat_interval_ms: 2000 }),
        )
    }

    async fn heartbeat(&self, req: Request<pb::HeartbeatRequest>) -> Res<pb::HeartbeatResponse> {
        let r = self.0.heartbeat(req.into_inner().worker_id);
        done(&self.0, "Heartbeat", r.map(|()| pb::HeartbeatResponse {}))
    }

    async fn get_assignment(
        &self,
        req: Request<pb::GetAssignmentRequest>,
    ) -> Res<pb::GetAssignmentResponse> {
        let worker = req.into_inner().worker_id;
        // A cell is leased only when there is no training assignment to give.
        let r = self.0.assignment(worker).map(|a| {
            let eval = if a.is_none() { self.0.eval_work(worker) } else { None };
            (a, eval)
        });
        let r = r.map(|pair| match pair {
            (Some(a), _) => pb::GetAssignmentResponse {
                has_assignment: true,
                retry_after_ms: 0,
                assignment: Some(sf_proto::assignment_to_wire(&a)),
                eval: None,
            },
            (None, Some(w)) => pb::GetAssignmentResponse {
                has_assignment: true,
                retry_after_ms: 0,
                assignment: None,
                eval: Some(sf_proto::eval_work_to_wire(&w)),
            },
            // An evaluation's last cells are leased to others: ask again soon, one may come back.
            (None, None) => pb::GetAssignmentResponse {
                has_assignment: false,
                retry_after_ms: if self.0.evaluating().is_some() { 250 } else { 1000 },
                assignment: None,
                eval: None,
            },
        });
        done(&self.0, "GetAssignment", r)
    }

    async fn push_eval_results(&self, req: Request<pb::EvalResults>) -> Res<pb::EvalAck> {
        let m = req.into_inner();
        let episodes = m
            .episodes
            .iter()
            .map(sf_proto::eval_episode_from_wire)
            .collect::<Result<Vec<_>, WireError>>();
        let r = match episodes {
            Ok(eps) => self.0.eval_results(m.job_id, m.worker_id, m.cell_id, eps, m.error).await,
            Err(e) => Err(e.into()),
        };
        done(&self.0, "PushEvalResults", r.map(|stored| pb::EvalAck { stored }))
    }

    type PushTransitionsStream = BoxStream<pb::PushAck>;

    async fn push_transitions(
        &self,
        req: Request<Streaming<pb::TransitionBatch>>,
    ) -> Res<Self::PushTransitionsStream> {
        let mut inbound = req.into_inner();
        let (tx, rx) = mpsc::channel(2);
        let inner = Arc::clone(&self.0);
        tokio::spawn(async move {
            loop {
                let msg = match inbound.next().await {
                    None => return,
                    Some(Ok(m)) => m,
                    Some(Err(s)) => {
                        // tonic reports an oversized message as OUT_OF_RANGE; the protocol says
                        // RESOURCE_EXHAUSTED.
                        let s = if s.code() == Code::OutOfRange {
                            Status::resource_exhausted(s.message().to_string())
                        } else {
                            s
                        };
                        inner.metrics.common.rpc("PushTransitions", s.code());
                        let _ = tx.send(Err(s)).await;
                        return;
                    }
                };
                let r = inner.ingest(msg).await;
                let ok = r.is_ok();
                let item = match r {
                    Ok(a) => {
                        inner.metrics.common.rpc("PushTransitions", Code::Ok);
                        Ok(pb::PushAck {
                            accepted: a.accepted,
                            dropped_stale: a.dropped_stale,
                            latest_policy_version: a.latest_policy_version,
                            warmup: a.warmup,
                        })
                    }
                    Err(e) => {
                        inner.metrics.common.rpc("PushTransitions", e.code());
                        Err(Status::from(e))
                    }
                };
                if tx.send(item).await.is_err() || !ok {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn get_policy(&self, req: Request<pb::GetPolicyRequest>) -> Res<pb::Policy> {
        let r = req.into_inner();
        let out = self
            .0
            .policy(r.job_id, sf_proto::policy_request_from_wire(r.version))
            .await
            .map_err(ServiceError::from);
        done(
            &self.0,
            "GetPolicy",
            out.map(|(v, w)| pb::Policy { job_id: r.job_id, version: v, weights: w.to_vec() }),
        )
    }
}
