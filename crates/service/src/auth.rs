//! Bearer-token authentication: the server-side check and the client-side header.
//!
//! Every RPC carries `authorization: Bearer <token>`; the server compares in constant time and
//! answers UNAUTHENTICATED before any handler runs, so a refused call changes nothing. Over
//! plaintext the token is accepted only from loopback peers unless the operator allows it
//! ([`Transport`]): a token sent in the clear across a network is refused, loudly.

use std::net::SocketAddr;
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
            let s = std::fs::read_to_string(p)
                .map_err(|source| TokenError::File { path: p.display().to_string(), source })?;
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

/// How the server's connections travel, for the plaintext-token rule.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transport {
    Tls,
    /// `allow_remote`: the operator accepts tokens in the clear from any peer.
    Plaintext {
        allow_remote: bool,
    },
}

impl Transport {
    /// Whether a token may be accepted from `peer` (unknown peers are not on loopback).
    pub fn accepts_token_from(self, peer: Option<SocketAddr>) -> bool {
        match self {
            Transport::Tls | Transport::Plaintext { allow_remote: true } => true,
            Transport::Plaintext { allow_remote: false } => {
                peer.is_some_and(|p| p.ip().to_canonical().is_loopback())
            }
        }
    }
}

/// Server-side check. `on_reject` counts refusals (metrics).
#[derive(Clone)]
pub struct RequireToken {
    want: Arc<[u8]>,
    on_reject: Arc<dyn Fn() + Send + Sync>,
    transport: Transport,
}

impl RequireToken {
    /// Plaintext from loopback only, until [`RequireToken::transport`] says otherwise.
    pub fn new(token: &Token, on_reject: impl Fn() + Send + Sync + 'static) -> Self {
        Self {
            want: Arc::from(format!("Bearer {}", token.0).into_bytes()),
            on_reject: Arc::new(on_reject),
            transport: Transport::Plaintext { allow_remote: false },
        }
    }

    pub fn transport(mut self, t: Transport) -> Self {
        self.transport = t;
        self
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
        let peer = req.remote_addr();
        if !self.transport.accepts_token_from(peer) {
            (self.on_reject)();
            let from = peer.map_or_else(|| "an unknown peer".to_string(), |p| p.ip().to_string());
            return Err(Status::unauthenticated(format!(
                "bearer token over plaintext from {from} refused: the learner serves TLS-less tokens to loopback only (serve TLS, or start it with --allow-plaintext-token on a trusted network)"
            )));
        }
        let ok = req
            .metadata()
            .get("authorization")
            .is_some_and(|v| constant_time_eq(v.as_bytes(), &self.want));
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
    fn plaintext_tokens_come_from_loopback_only_unless_allowed() {
        let strict = Transport::Plaintext { allow_remote: false };
        for (peer, ok) in [
            ("127.0.0.1:5", true),
            ("[::1]:5", true),
            ("[::ffff:127.0.0.1]:5", true),
            ("10.0.0.7:5", false),
            ("[2001:db8::1]:5", false),
        ] {
            assert_eq!(strict.accepts_token_from(Some(peer.parse().expect("addr"))), ok, "{peer}");
        }
        assert!(!strict.accepts_token_from(None));
        assert!(Transport::Plaintext { allow_remote: true }
            .accepts_token_from(Some("10.0.0.7:5".parse().expect("addr"))));
        assert!(Transport::Tls.accepts_token_from(None));
    }

    #[test]
    fn only_the_right_token_passes() {
        let t = Token::new("s3cret-token", "test").expect("valid");
        let mut check =
            RequireToken::new(&t, || {}).transport(Transport::Plaintext { allow_remote: true });
        let mut attach = AttachToken::new(Some(t));
        let req = attach.call(Request::new(())).expect("attach");
        assert!(check.call(req).is_ok());
        assert_eq!(
            check.call(Request::new(())).expect_err("none").code(),
            tonic::Code::Unauthenticated
        );
        let mut wrong = AttachToken::new(Some(Token::new("s3cret-tokeN", "t").expect("valid")));
        let req = wrong.call(Request::new(())).expect("attach");
        assert_eq!(check.call(req).expect_err("wrong").code(), tonic::Code::Unauthenticated);
        assert!(Token::new("short", "t").is_err());
        // A request with no known peer (as here) is not on loopback: refused over plaintext
        // unless allowed, accepted under TLS.
        let mut strict =
            RequireToken::new(&Token::new("s3cret-token", "test").expect("valid"), || {});
        let e = strict
            .call(attach.call(Request::new(())).expect("attach"))
            .expect_err("plaintext from an unknown peer");
        assert!(e.message().contains("--allow-plaintext-token"), "{e:?}");
        let mut tls = RequireToken::new(&Token::new("s3cret-token", "test").expect("valid"), || {})
            .transport(Transport::Tls);
        assert!(tls.call(attach.call(Request::new(())).expect("attach")).is_ok());
        assert!(Token::new("has space inside", "t").is_err());
    }
}
