//! socialflow-report: the statistics of the paper's evaluation protocol.
//!
//! Owns: the t-statistics ([`stats`]: [`stats::Summary`], the paired, one-sample and Welch
//! t-tests), corrections and combinations over several tests ([`inference`]), the
//! charts ([`plot`]), TensorBoard event files ([`tensorboard`]), the paper's findings as tested
//! claims ([`findings`]), the evaluation's result files ([`episodes`]) and the reproduction
//! report built from them ([`report`]). Must not: run simulations; callers pass
//! per-episode values.

pub mod episodes;
pub mod findings;
pub mod inference;
pub mod plot;
pub mod report;
pub mod stats;
pub mod tensorboard;
