//! How a client (worker, remote CLI) reaches the learner: URL, bearer token, TLS trust root.
//! One set of flags and environment variables for every client command.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use tonic::transport::Endpoint;

use crate::auth::{Token, TOKEN_ENV};

#[derive(Args, Debug, Clone)]
pub struct LearnerConn {
    /// The learner's gRPC URL.
    #[arg(long, env = "SOCIALFLOW_LEARNER_URL", default_value = "http://127.0.0.1:50051")]
    pub learner: String,
    /// File holding the bearer token (default: the SOCIALFLOW_TOKEN variable).
    #[arg(long, env = "SOCIALFLOW_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// CA certificate (PEM) for an https:// learner.
    #[arg(long, env = "SOCIALFLOW_TLS_CA_FILE")]
    pub tls_ca_file: Option<PathBuf>,
    /// Client certificate (PEM) for a learner that requires mutual TLS.
    #[arg(long, env = "SOCIALFLOW_TLS_CLIENT_CERT_FILE", requires = "tls_client_key_file")]
    pub tls_client_cert_file: Option<PathBuf>,
    #[arg(long, env = "SOCIALFLOW_TLS_CLIENT_KEY_FILE", requires = "tls_client_cert_file")]
    pub tls_client_key_file: Option<PathBuf>,
}

impl LearnerConn {
    /// The bearer token from `--token-file` or `SOCIALFLOW_TOKEN`.
    pub fn token(&self) -> anyhow::Result<Token> {
        Token::load(TOKEN_ENV, self.token_file.as_deref()).context("the learner's bearer token")
    }

    /// TLS trust root and client identity from the flags.
    pub fn tls(&self) -> crate::tls::ClientTls {
        let identity = self.tls_client_cert_file.clone().zip(self.tls_client_key_file.clone());
        crate::tls::ClientTls { ca_file: self.tls_ca_file.clone(), identity }
    }

    /// The endpoint (TLS for https://, with the CA file and client identity).
    pub fn endpoint(&self) -> anyhow::Result<Endpoint> {
        crate::tls::endpoint(&self.learner, &self.tls())
    }
}
