//! Bearer-token authentication: the server-side check and the client-side header.
//!
//! Every RPC carries `authorization: Bearer <token>`; the server compares in constant time and
//! answers UNAUTHENTICATED before any handler runs, so a refused call changes nothing.

use std::path::Path;
use std::sync::Arc;

use tonic::metadata::MetadataValue;
use tonic::service::Interceptor;
use tonic::{Request, Status};

/// The environment variable that holds the bearer token.
pub const TOKEN_ENV: &str = "SOCIALFLOW_TOKEN";

/// A shared secret. Never printed.
#[derive(Clone)]
pub struct Token(Arc<str>);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(..)")
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    #[error("no token: set {env} or pass a token file")]
    Missing { env: String },
    #[error("reading token file {path}: {source}")]
    File { path: String, source: std::io::Error },
    #[error("token from {0} must be 8 to 512 printable ASCII characters without spaces")]
    Malformed(String),
}

impl Token {
    pub fn new(s: &str, origin: &str) -> Result<Self, TokenError> {
        let s = s.trim();
        if s.len() < 8 || s.len() > 512 || !s.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(TokenError::Malformed(origin.to_string()));
        }
        Ok(Self(Arc::from(s)))
    }

    /// The token from `file` if given, else from the environment variable `env`.
    pub fn load(env: &str, file: Option<&Path>) -> Result<Self, TokenError> {
        if let Some(p) = file {
            let s = std::fs::read_to_string(p).map_err(|source| TokenError::File { path: p.display().to_string(), source })?;
            return Self::new(&s, &p.display().to_string());
        }
        match std::env::var(env) {
            Ok(s) => Self::new(&s, env),
            Err(_) => Err(TokenError::Missing { env: env.to_string() }),
        }
    }

    fn header(&self) -> MetadataValue<tonic::metadata::Ascii> {
        format!("Bearer {}", self.0).parse().expect("a validated token is printable ASCII")
    }
}

/// Server-side check. `on_reject` counts refusals (metrics).
#[derive(Clone)]
pub struct RequireToken {
    want: Arc<[u8]>,
    on_reject: Arc<dyn Fn() + Send + Sync>,
}

impl RequireToken {
    pub fn new(token: &Token, on_reject: impl Fn() + Send + Sync + 'static) -> Self {
        Self { want: Arc::from(format!("Bearer {}", token.0).into_bytes()), on_reject: Arc::new(on_reject) }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl Interceptor for RequireToken {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        let ok = req.metadata().get("authorization").is_some_and(|v| constant_time_eq(v.as_bytes(), &self.want));
        if ok {
            Ok(req)
        } else {
            (self.on_reject)();
            Err(Status::unauthenticated("missing or wrong bearer token"))
        }
    }
}

/// Client-side: attaches the token to every call.
#[derive(Clone, Debug)]
pub struct AttachToken(Option<Token>);

impl AttachToken {
    pub fn new(token: Option<Token>) -> Self {
        Self(token)
    }
}

impl Interceptor for AttachToken {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(t) = &self.0 {
            req.metadata_mut().insert("authorization", t.header());
        }
        Ok(req)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_right_token_passes() {
        let t = Token::new("s3cret-token", "test").expect("valid");
        let mut check = RequireToken::new(&t, || {});
        let mut attach = AttachToken::new(Some(t));
        let req = attach.call(Request::new(())).expect("attach");
        assert!(check.call(req).is_ok());
        assert_eq!(check.call(Request::new(())).expect_err("none").code(), tonic::Code::Unauthenticated);
        let mut wrong = AttachToken::new(Some(Token::new("s3cret-tokeN", "t").expect("valid")));
        let req = wrong.call(Request::new(())).expect("attach");
        assert_eq!(check.call(req).expect_err("wrong").code(), tonic::Code::Unauthenticated);
        assert!(Token::new("short", "t").is_err());
        assert!(Token::new("has space inside", "t").is_err());
    }
}
