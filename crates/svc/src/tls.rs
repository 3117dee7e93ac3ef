//! Optional TLS (rustls, ring): the learner's server identity and clients' trust roots.
//!
//! A learner with `tls_cert_file` + `tls_key_file` serves only TLS; clients reach it with an
//! `https://` URL and the CA (or the self-signed certificate) in `--tls-ca-file`.

use std::path::Path;
use std::time::Duration;

use anyhow::{bail, Context};
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity, ServerTlsConfig};

fn read(path: &Path, what: &str) -> anyhow::Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading the {what} {}", path.display()))
}

/// The server side from PEM files.
pub fn server(cert: &Path, key: &Path) -> anyhow::Result<ServerTlsConfig> {
    Ok(ServerTlsConfig::new().identity(Identity::from_pem(read(cert, "TLS certificate")?, read(key, "TLS key")?)))
}

/// A client endpoint for `url`: TLS with `ca` as the trust root for `https://`, plain for
/// `http://`.
pub fn endpoint(url: &str, ca: Option<&Path>) -> anyhow::Result<Endpoint> {
    let ep = Endpoint::from_shared(url.to_string()).with_context(|| format!("learner url `{url}`"))?.connect_timeout(Duration::from_secs(5)).tcp_nodelay(true);
    match (url.starts_with("https://"), ca) {
        (true, Some(ca)) => Ok(ep.tls_config(ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read(ca, "TLS CA certificate")?))).context("TLS client configuration")?),
        (true, None) => bail!("`{url}` is https: pass the learner's CA certificate with --tls-ca-file"),
        (false, Some(_)) => bail!("--tls-ca-file given but `{url}` is not https"),
        (false, None) => Ok(ep),
    }
}
