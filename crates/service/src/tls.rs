//! Optional TLS (rustls, ring): the learner's server identity and clients' trust roots.
//!
//! A learner with `tls_cert_file` + `tls_key_file` serves only TLS; clients reach it with an
//! `https://` URL and the CA (or the self-signed certificate) in `--tls-ca-file`. With
//! `tls_client_ca_file` as well it is mutual TLS: only clients presenting a certificate signed by
//! that CA (`--tls-client-cert-file` + `--tls-client-key-file`) complete the handshake.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity, ServerTlsConfig};

fn read(path: &Path, what: &str) -> anyhow::Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading the {what} {}", path.display()))
}

/// The server side from PEM files; `client_ca`: require client certificates signed by it.
pub fn server(
    cert: &Path,
    key: &Path,
    client_ca: Option<&Path>,
) -> anyhow::Result<ServerTlsConfig> {
    let tls = ServerTlsConfig::new()
        .identity(Identity::from_pem(read(cert, "TLS certificate")?, read(key, "TLS key")?));
    Ok(match client_ca {
        Some(ca) => {
            tls.client_ca_root(Certificate::from_pem(read(ca, "TLS client CA certificate")?))
        }
        None => tls,
    })
}

/// How a client trusts the learner and, for mutual TLS, proves who it is.
#[derive(Clone, Debug, Default)]
pub struct ClientTls {
    /// Trust root for an `https://` learner.
    pub ca_file: Option<PathBuf>,
    /// Client certificate chain and key (PEM), for a learner that requires them.
    pub identity: Option<(PathBuf, PathBuf)>,
}

/// A client endpoint for `url`: TLS with the CA as the trust root (and the client identity, if
/// any) for `https://`, plain for `http://`.
pub fn endpoint(url: &str, tls: &ClientTls) -> anyhow::Result<Endpoint> {
    let ep = Endpoint::from_shared(url.to_string())
        .with_context(|| format!("learner url `{url}`"))?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true);
    match (url.starts_with("https://"), &tls.ca_file) {
        (true, Some(ca)) => {
            let mut c = ClientTlsConfig::new()
                .ca_certificate(Certificate::from_pem(read(ca, "TLS CA certificate")?));
            if let Some((cert, key)) = &tls.identity {
                c = c.identity(Identity::from_pem(
                    read(cert, "TLS client certificate")?,
                    read(key, "TLS client key")?,
                ));
            }
            Ok(ep.tls_config(c).context("TLS client configuration")?)
        }
        (true, None) => {
            bail!("`{url}` is https: pass the learner's CA certificate with --tls-ca-file")
        }
        (false, Some(_)) => bail!("--tls-ca-file given but `{url}` is not https"),
        (false, None) if tls.identity.is_some() => {
            bail!("--tls-client-cert-file given but `{url}` is not https")
        }
        (false, None) => Ok(ep),
    }
}
