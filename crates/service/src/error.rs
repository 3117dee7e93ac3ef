//! The one table from domain errors to gRPC status codes (documented in the `.proto`).
//! Messages are lowercase without a trailing period.

use tonic::{Code, Status};

#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("{0}")]
    InvalidArgument(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    FailedPrecondition(String),
    #[error("{0}")]
    ResourceExhausted(String),
    #[error("{0}")]
    Unavailable(String),
    #[error("{0}")]
    DeadlineExceeded(String),
    #[error("{0}")]
    Internal(String),
    #[error("{0}")]
    Unauthenticated(String),
}

impl ServiceError {
    pub fn code(&self) -> Code {
        match self {
            Self::InvalidArgument(_) => Code::InvalidArgument,
            Self::NotFound(_) => Code::NotFound,
            Self::FailedPrecondition(_) => Code::FailedPrecondition,
            Self::ResourceExhausted(_) => Code::ResourceExhausted,
            Self::Unavailable(_) => Code::Unavailable,
            Self::DeadlineExceeded(_) => Code::DeadlineExceeded,
            Self::Internal(_) => Code::Internal,
            Self::Unauthenticated(_) => Code::Unauthenticated,
        }
    }

    /// The constructor of this error's kind: a wrapper that passes a handler's error on with a
    /// new message keeps its status.
    pub fn kind(&self) -> fn(String) -> ServiceError {
        match self {
            Self::InvalidArgument(_) => Self::InvalidArgument,
            Self::NotFound(_) => Self::NotFound,
            Self::FailedPrecondition(_) => Self::FailedPrecondition,
            Self::ResourceExhausted(_) => Self::ResourceExhausted,
            Self::Unavailable(_) => Self::Unavailable,
            Self::DeadlineExceeded(_) => Self::DeadlineExceeded,
            Self::Internal(_) => Self::Internal,
            Self::Unauthenticated(_) => Self::Unauthenticated,
        }
    }
}

impl From<ServiceError> for Status {
    fn from(e: ServiceError) -> Self {
        Status::new(e.code(), e.to_string())
    }
}

impl From<sf_proto::WireError> for ServiceError {
    fn from(e: sf_proto::WireError) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

impl From<sf_job::ConfigError> for ServiceError {
    fn from(e: sf_job::ConfigError) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

impl From<sf_job::SpecError> for ServiceError {
    fn from(e: sf_job::SpecError) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

impl From<sf_job::BatchError> for ServiceError {
    fn from(e: sf_job::BatchError) -> Self {
        Self::InvalidArgument(e.to_string())
    }
}

/// Lower-case snake name of a code, the `code` label of RPC metrics.
pub fn code_label(c: Code) -> &'static str {
    match c {
        Code::Ok => "ok",
        Code::Cancelled => "cancelled",
        Code::Unknown => "unknown",
        Code::InvalidArgument => "invalid_argument",
        Code::DeadlineExceeded => "deadline_exceeded",
        Code::NotFound => "not_found",
        Code::AlreadyExists => "already_exists",
        Code::PermissionDenied => "permission_denied",
        Code::ResourceExhausted => "resource_exhausted",
        Code::FailedPrecondition => "failed_precondition",
        Code::Aborted => "aborted",
        Code::OutOfRange => "out_of_range",
        Code::Unimplemented => "unimplemented",
        Code::Internal => "internal",
        Code::Unavailable => "unavailable",
        Code::DataLoss => "data_loss",
        Code::Unauthenticated => "unauthenticated",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn domain_errors_map_to_the_documented_codes() {
        let s: Status =
            ServiceError::from(sf_proto::WireError { field: "obs_f16", reason: "short".into() })
                .into();
        assert_eq!(s.code(), Code::InvalidArgument);
        assert!(s.message().contains("obs_f16"));
        let s: Status = ServiceError::NotFound("job 7 not found".into()).into();
        assert_eq!(s.code(), Code::NotFound);
        assert_eq!(code_label(Code::ResourceExhausted), "resource_exhausted");
    }
}
