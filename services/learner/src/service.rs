//! The learner's gRPC handlers: `JobService` and `ExperienceService`.
//!
//! Owns: request decoding (through `sf_proto`), the call into the part each service serves
//! (`JobService`: the job table, [`crate::jobs::Jobs`]; `ExperienceService`: the worker side,
//! [`crate::experience::Experience`]), the mapping of results to responses and the per-method
//! RPC counts; errors become statuses only through `sf_service::ServiceError`. Must not: decide
//! anything a part decides, block the runtime (store IO and ingest go through `spawn_blocking`)
//! or run tensor code.

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use sf_job::{CellId, JobId};
use sf_proto::pb::experience_service_server::ExperienceService;
use sf_proto::pb::job_service_server::JobService;
use sf_proto::{pb, WireError};
use sf_service::ServiceError;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Code, Request, Response, Status, Streaming};

use crate::experience::Work;
use crate::metrics::LearnerMetrics;

type Res<T> = Result<Response<T>, Status>;
type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

/// `JobService` over the job table.
#[derive(Clone)]
pub struct Jobs {
    pub jobs: Arc<crate::jobs::Jobs>,
    pub metrics: LearnerMetrics,
}

/// `ExperienceService` over the worker side.
#[derive(Clone)]
pub struct Experience {
    pub experience: Arc<crate::experience::Experience>,
    pub metrics: LearnerMetrics,
}

/// Counts the outcome and converts the error.
fn done<T, E: Into<ServiceError>>(m: &LearnerMetrics, method: &str, r: Result<T, E>) -> Res<T> {
    match r.map_err(Into::into) {
        Ok(v) => {
            m.common.rpc(method, Code::Ok);
            Ok(Response::new(v))
        }
        Err(e) => {
            m.common.rpc(method, e.code());
            Err(e.into())
        }
    }
}

#[tonic::async_trait]
impl JobService for Jobs {
    async fn submit_job(&self, req: Request<pb::SubmitJobRequest>) -> Res<pb::Job> {
        let r = self.jobs.submit(req.into_inner().config_toml).await;
        done(&self.metrics, "SubmitJob", r.map(|j| sf_proto::job_to_wire(&j)))
    }

    async fn get_job(&self, req: Request<pb::GetJobRequest>) -> Res<pb::Job> {
        let r = self.jobs.get(JobId::from(req.into_inner().job_id));
        done(&self.metrics, "GetJob", r.map(|j| sf_proto::job_to_wire(&j)))
    }

    async fn list_jobs(&self, _req: Request<pb::ListJobsRequest>) -> Res<pb::ListJobsResponse> {
        let r: Result<_, ServiceError> = Ok(self.jobs.list());
        // Summaries: configs can be megabytes each, and a list of them would outgrow a default
        // client's 4 MiB receive limit. GetJob carries the config.
        let summary = |j: &sf_job::JobRecord| pb::Job {
            config_toml: String::new(),
            ..sf_proto::job_to_wire(j)
        };
        done(
            &self.metrics,
            "ListJobs",
            r.map(|js| pb::ListJobsResponse { jobs: js.iter().rev().map(summary).collect() }),
        )
    }

    async fn cancel_job(&self, req: Request<pb::CancelJobRequest>) -> Res<pb::Job> {
        let r = self.jobs.cancel(JobId::from(req.into_inner().job_id)).await;
        done(&self.metrics, "CancelJob", r.map(|j| sf_proto::job_to_wire(&j)))
    }

    async fn get_job_file(&self, req: Request<pb::GetJobFileRequest>) -> Res<pb::JobFile> {
        let pb::GetJobFileRequest { job_id, name } = req.into_inner();
        let r = self.jobs.job_file(JobId::from(job_id), &name).await;
        done(&self.metrics, "GetJobFile", r.map(|content| pb::JobFile { job_id, name, content }))
    }

    type WatchJobStream = BoxStream<pb::JobProgress>;

    async fn watch_job(&self, req: Request<pb::WatchJobRequest>) -> Res<Self::WatchJobStream> {
        let id = JobId::from(req.into_inner().job_id);
        let first = match self.jobs.get(id) {
            Ok(j) => j,
            Err(e) => return done(&self.metrics, "WatchJob", Err(e)),
        };
        let (tx, rx) = mpsc::channel(4);
        let jobs = Arc::clone(&self.jobs);
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
                cur = match jobs.get(id) {
                    Ok(j) => j,
                    Err(e) => {
                        let _ = tx.send(Err(ServiceError::from(e).into())).await;
                        return;
                    }
                };
            }
        });
        done::<_, ServiceError>(
            &self.metrics,
            "WatchJob",
            Ok(Box::pin(ReceiverStream::new(rx)) as Self::WatchJobStream),
        )
    }
}

#[tonic::async_trait]
impl ExperienceService for Experience {
    async fn register(&self, req: Request<pb::RegisterRequest>) -> Res<pb::RegisterResponse> {
        let r = req.into_inner();
        let seats = sf_job::eval::ScriptedSeats { idm: r.runs_idm_ego, mobil: r.runs_mobil_ego };
        let id = self.experience.register(&r.name, seats);
        done::<_, ServiceError>(
            &self.metrics,
            "Register",
            Ok(pb::RegisterResponse { worker_id: id.get(), heartbeat_interval_ms: 2000 }),
        )
    }

    async fn heartbeat(&self, req: Request<pb::HeartbeatRequest>) -> Res<pb::HeartbeatResponse> {
        let r = self.experience.heartbeat(req.into_inner().worker_id.into());
        done(&self.metrics, "Heartbeat", r.map(|()| pb::HeartbeatResponse {}))
    }

    async fn get_assignment(
        &self,
        req: Request<pb::GetAssignmentRequest>,
    ) -> Res<pb::GetAssignmentResponse> {
        let r =
            self.experience.assignment(req.into_inner().worker_id.into()).map(|work| match work {
                Work::Train(a) => pb::GetAssignmentResponse {
                    has_assignment: true,
                    retry_after_ms: 0,
                    assignment: Some(sf_proto::assignment_to_wire(&a)),
                    eval: None,
                },
                Work::Eval(w) => pb::GetAssignmentResponse {
                    has_assignment: true,
                    retry_after_ms: 0,
                    assignment: None,
                    eval: Some(sf_proto::eval_work_to_wire(&w)),
                },
                Work::Wait { retry_after_ms } => pb::GetAssignmentResponse {
                    has_assignment: false,
                    retry_after_ms,
                    assignment: None,
                    eval: None,
                },
            });
        done(&self.metrics, "GetAssignment", r)
    }

    async fn push_eval_results(&self, req: Request<pb::EvalResults>) -> Res<pb::EvalAck> {
        let m = req.into_inner();
        let episodes = m
            .episodes
            .iter()
            .map(sf_proto::eval_episode_from_wire)
            .collect::<Result<Vec<_>, WireError>>();
        let r = match episodes {
            Ok(eps) => {
                let worker = m.worker_id.into();
                self.experience
                    .eval_results(
                        JobId::from(m.job_id),
                        worker,
                        CellId::from(m.cell_id),
                        eps,
                        m.error,
                    )
                    .await
            }
            Err(e) => Err(e.into()),
        };
        done(&self.metrics, "PushEvalResults", r.map(|stored| pb::EvalAck { stored }))
    }

    type PushTransitionsStream = BoxStream<pb::PushAck>;

    async fn push_transitions(
        &self,
        req: Request<Streaming<pb::TransitionBatch>>,
    ) -> Res<Self::PushTransitionsStream> {
        let mut inbound = req.into_inner();
        let (tx, rx) = mpsc::channel(2);
        let (exp, metrics) = (Arc::clone(&self.experience), self.metrics.clone());
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
                        metrics.common.rpc("PushTransitions", s.code());
                        let _ = tx.send(Err(s)).await;
                        return;
                    }
                };
                let r = exp.ingest(msg).await;
                let ok = r.is_ok();
                let item = match r {
                    Ok(a) => {
                        metrics.common.rpc("PushTransitions", Code::Ok);
                        Ok(pb::PushAck {
                            accepted: a.accepted,
                            dropped_stale: a.dropped_stale,
                            latest_policy_version: a.latest_policy_version.get(),
                            warmup: a.warmup,
                        })
                    }
                    Err(e) => {
                        metrics.common.rpc("PushTransitions", e.code());
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
        let which = sf_proto::policy_request_from_wire(r.version);
        let out = self.experience.policy(JobId::from(r.job_id), which).await;
        done(
            &self.metrics,
            "GetPolicy",
            out.map(|(v, w)| pb::Policy {
                job_id: r.job_id,
                version: v.get(),
                weights: w.to_vec(),
            }),
        )
    }
}
