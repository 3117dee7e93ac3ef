//! Weights as bytes (burnpack records): how the learner ships a policy version to workers.

use burn::module::Module;
use burn::store::ModuleRecord;
use burn::tensor::Bytes;

#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    #[error("cannot encode weights: {0}")]
    Encode(String),
    #[error("cannot decode weights: {0}")]
    Decode(String),
}

/// Serialises a module's parameters.
pub fn to_bytes<M: Module + Clone>(m: &M) -> Result<Vec<u8>, WeightsError> {
    let bytes =
        m.clone().into_record().into_bytes().map_err(|e| WeightsError::Encode(format!("{e:?}")))?;
    Ok(bytes.to_vec())
}

/// The SHA-256 of weight bytes, in lowercase hex: how files and logs name a set of weights.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// Loads parameters into a module of the same architecture.
pub fn from_bytes<M: Module>(m: M, bytes: &[u8]) -> Result<M, WeightsError> {
    let rec = ModuleRecord::from_bytes(Bytes::from_bytes_vec(bytes.to_vec()))
        .map_err(|e| WeightsError::Decode(format!("{e:?}")))?;
    m.try_load_record(rec).map_err(|e| WeightsError::Decode(format!("{e:?}")))
}
