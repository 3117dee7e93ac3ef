//! Fuzzing of the wire decoding (property tests, stable Rust, deterministic, bounded for CI).
//!
//! What is fuzzed: `prost` decoding of random bytes and of byte-mutated encodings of valid
//! messages as `TransitionBatch`, `Assignment`, `EvalAssignment` (a worker's `EvalWork`),
//! `EvalResults`, `Job` and `JobProgress`, each followed by its `sf_proto::*_from_wire`
//! conversion; and field-level damage to a valid `TransitionBatch` (`count`, `obs_len`,
//! `action_dim` set to other or huge values, arrays one row short or long, bad flags, non-finite
//! values, out-of-range episode fractions).
//!
//! What is asserted: nothing panics; every conversion error names a field (`WireError::field`
//! is non-empty and appears in the message, the reason is non-empty); a valid message survives
//! encode -> decode -> convert unchanged; a damaged batch is refused with an error naming the
//! field the damage shows in.
//!
//! Cases: 1024 per property (fixed seed, no persistence file); together well under a second in
//! the debug profile.

use half::f16;
use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{Config as ProptestConfig, RngSeed};
use prost::Message;
use sf_job::eval::{Cell, EvalEpisode, EvalWork};
use sf_job::{Assignment, Ends, EpisodeResult, Frozen, FrozenRole, SvoGaussian, TransitionBatch};
use sf_proto::{pb, WireError};

/// Deterministic and bounded for CI: a fixed seed and `cases` cases, no regression files
/// written into the crate. `PROPTEST_CASES` and `PROPTEST_RNG_SEED` override both for a longer
/// local run.
fn config(cases: u32) -> ProptestConfig {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse().ok());
    ProptestConfig {
        cases: env("PROPTEST_CASES").map_or(cases, |c: u64| c as u32),
        rng_seed: RngSeed::Fixed(env("PROPTEST_RNG_SEED").unwrap_or(0x50c1_a1f1)),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// An error must name its field.
fn named(r: Result<(), WireError>) -> Result<(), TestCaseError> {
    if let Err(e) = r {
        prop_assert!(!e.field.is_empty(), "error without a field: {e:?}");
        prop_assert!(!e.reason.is_empty(), "error without a reason: {e:?}");
        prop_assert!(e.to_string().contains(e.field), "message does not name the field: {e}");
    }
    Ok(())
}

/// Decodes `bytes` as every message the services read from peers and converts what decodes.
fn decode_all(bytes: &[u8]) -> Result<(), TestCaseError> {
    if let Ok(m) = pb::TransitionBatch::decode(bytes) {
        named(sf_proto::batch_from_wire(m).map(drop))?;
    }
    if let Ok(m) = pb::Assignment::decode(bytes) {
        named(sf_proto::assignment_from_wire(&m).map(drop))?;
    }
    if let Ok(m) = pb::EvalAssignment::decode(bytes) {
        named(sf_proto::eval_work_from_wire(&m).map(drop))?;
    }
    if let Ok(m) = pb::EvalResults::decode(bytes) {
        for e in &m.episodes {
            named(sf_proto::eval_episode_from_wire(e).map(drop))?;
        }
    }
    if let Ok(m) = pb::Job::decode(bytes) {
        named(sf_proto::job_from_wire(&m).map(drop))?;
    }
    if let Ok(m) = pb::JobProgress::decode(bytes) {
        named(sf_proto::progress_from_wire(&m).map(drop))?;
    }
    Ok(())
}

fn fraction() -> impl Strategy<Value = f32> {
    0.0f32..=1.0
}

fn episode_result() -> impl Strategy<Value = EpisodeResult> {
    (
        any::<u32>(),
        fraction(),
        fraction(),
        fraction(),
        [fraction(), fraction(), fraction(), fraction(), fraction()],
    )
        .prop_map(|(scenario_index, success, safety, speed, ends)| EpisodeResult {
            scenario_index,
            scores: sf_job::Scores { success, safety, speed },
            ends: Ends::from_values(ends),
        })
}

/// A valid batch: 1-8 rows of 1-6 observation floats and 1-3 action floats, finite values.
fn valid_batch() -> impl Strategy<Value = TransitionBatch> {
    (1u64.., any::<u64>(), 1usize..=6, 1usize..=3, 1usize..=8).prop_flat_map(
        |(job_id, worker_id, obs_len, action_dim, n)| {
            (
                Just((job_id, worker_id, obs_len, action_dim)),
                prop::collection::vec(-1000.0f32..1000.0, n * obs_len),
                prop::collection::vec(-1000.0f32..1000.0, n * obs_len),
                prop::collection::vec(-1.0f32..=1.0, n * action_dim),
                prop::collection::vec(-100.0f32..100.0, n),
                prop::collection::vec(any::<bool>(), n),
                prop::collection::vec(0u32..4, n),
                prop::collection::vec(episode_result(), 0..3),
                any::<u64>(),
                any::<u64>(),
            )
                .prop_map(
                    |(
                        (job_id, worker_id, obs_len, action_dim),
                        obs,
                        next_obs,
                        actions,
                        rewards,
                        terminals,
                        map_ids,
                        episodes,
                        policy_version,
                        sim_steps,
                    )| {
                        let mut b = TransitionBatch::new(
                            job_id.into(),
                            worker_id.into(),
                            obs_len,
                            action_dim,
                        );
                        for i in 0..rewards.len() {
                            let o = i * obs_len..(i + 1) * obs_len;
                            let a = i * action_dim..(i + 1) * action_dim;
                            b.push(
                                &obs[o.clone()],
                                &actions[a],
                                rewards[i],
                                &next_obs[o],
                                terminals[i],
                                map_ids[i],
                            );
                        }
                        b.episodes = episodes;
                        b.acted_by = sf_proto::acted_by_from_wire(policy_version);
                        b.sim_steps = sim_steps;
                        b
                    },
                )
        },
    )
}

fn svo_gaussian() -> impl Strategy<Value = (String, SvoGaussian)> {
    ("[a-z]{1,12}", 0.0f32..=90.0, 0.0f32..30.0)
        .prop_map(|(s, mean_deg, std_deg)| (s, SvoGaussian { mean_deg, std_deg }))
}

fn frozen() -> impl Strategy<Value = Frozen> {
    (
        prop_oneof![
            Just(FrozenRole::Background),
            Just(FrozenRole::Ego),
            Just(FrozenRole::Adversary)
        ],
        1u64..,
        "name = \"[a-z-]{1,16}\"",
        prop::collection::vec(svo_gaussian(), 0..3),
    )
        .prop_map(|(role, job_id, config_toml, svo_gaussians)| Frozen {
            role,
            job_id: job_id.into(),
            config_toml,
            svo_gaussians,
        })
}

fn valid_assignment() -> impl Strategy<Value = Assignment> {
    (
        1u64..,
        "[ -~\n]{0,64}",
        any::<u32>(),
        any::<u64>(),
        any::<u64>(),
        1u32..,
        1u32..,
        any::<bool>(),
        prop::collection::vec(frozen(), 0..3),
    )
        .prop_map(
            |(
                job_id,
                config_toml,
                scenario_index,
                seed,
                policy_version,
                obs_len,
                action_dim,
                warmup,
                frozen,
            )| Assignment {
                job_id: job_id.into(),
                config_toml,
                scenario_index,
                seed,
                policy_version: policy_version.into(),
                obs_len,
                action_dim,
                warmup,
                frozen,
            },
        )
}

fn valid_eval_work() -> impl Strategy<Value = EvalWork> {
    let cell = (
        "[a-z_]{1,12}",
        "[A-Za-z/]{0,12}",
        "[A-Za-z]{1,12}",
        "[a-z]{1,12}",
        prop::option::of(0u32..=90),
        prop::option::of(1usize..=64),
    )
        .prop_map(|(experiment, ego, flow, scenario, svo_deg, vehicles)| Cell {
            experiment,
            ego,
            flow,
            scenario,
            svo_deg,
            vehicles,
        });
    // Who sits in the ego's seat: nobody (a flow on its own), the IDM driver, or an EGO policy.
    let seat = prop_oneof![Just(None), Just(Some(true)), Just(Some(false))];
    (
        1u64..,
        any::<u64>(),
        cell,
        1u32..,
        1u32..,
        1u32..,
        prop::collection::vec(frozen(), 0..3),
        seat,
        frozen(),
    )
        .prop_map(
            |(job_id, cell_id, mut cell, cases, seeds, envs, mut policies, seat, ego)| {
                policies.retain(|p| p.role != FrozenRole::Ego);
                match seat {
                    None => cell.ego.clear(),
                    Some(_) if cell.ego.is_empty() => cell.ego = "E".into(),
                    Some(_) => {}
                }
                if seat == Some(false) {
                    policies.push(Frozen { role: FrozenRole::Ego, ..ego });
                }
                EvalWork {
                    job_id: job_id.into(),
                    cell_id: cell_id.into(),
                    cell,
                    cases,
                    seeds,
                    envs,
                    policies,
                    scripted_ego: (seat == Some(true)).then_some(sf_job::eval::ScriptedEgo::Idm),
                }
            },
        )
}

fn valid_eval_results() -> impl Strategy<Value = pb::EvalResults> {
    let episode = (
        any::<u32>(),
        any::<u32>(),
        fraction(),
        fraction(),
        fraction(),
        fraction(),
        prop::option::of(fraction()),
        prop::option::of(fraction()),
    )
        .prop_map(
            |(case, seed, success, safety, speed, collision, lane_change, road_closed)| {
                EvalEpisode {
                    case,
                    seed,
                    scores: sf_job::Scores { success, safety, speed },
                    collision,
                    lane_change,
                    road_closed,
                }
            },
        );
    (1u64.., any::<u64>(), any::<u64>(), prop::collection::vec(episode, 0..6)).prop_map(
        |(job_id, worker_id, cell_id, episodes)| pb::EvalResults {
            job_id,
            worker_id,
            cell_id,
            episodes: episodes.iter().map(sf_proto::eval_episode_to_wire).collect(),
            error: String::new(),
        },
    )
}

/// One edit of an encoded message.
#[derive(Clone, Debug)]
enum ByteEdit {
    FlipBit(Index, u8),
    Set(Index, u8),
    Insert(Index, u8),
    Delete(Index),
    Truncate(Index),
    /// Overwrites a varint-sized run (lengths and tags live there) with high bytes.
    Smear(Index, u8),
}

fn byte_edit() -> impl Strategy<Value = ByteEdit> {
    prop_oneof![
        (any::<Index>(), 0u8..8).prop_map(|(i, b)| ByteEdit::FlipBit(i, b)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, v)| ByteEdit::Set(i, v)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, v)| ByteEdit::Insert(i, v)),
        any::<Index>().prop_map(ByteEdit::Delete),
        any::<Index>().prop_map(ByteEdit::Truncate),
        (any::<Index>(), 1u8..=10).prop_map(|(i, n)| ByteEdit::Smear(i, n)),
    ]
}

fn apply(bytes: &mut Vec<u8>, edits: &[ByteEdit]) {
    for e in edits {
        let len = bytes.len();
        match e {
            ByteEdit::Insert(i, v) => bytes.insert(i.index(len + 1), *v),
            _ if len == 0 => {}
            ByteEdit::FlipBit(i, b) => bytes[i.index(len)] ^= 1 << b,
            ByteEdit::Set(i, v) => bytes[i.index(len)] = *v,
            ByteEdit::Delete(i) => {
                bytes.remove(i.index(len));
            }
            ByteEdit::Truncate(i) => bytes.truncate(i.index(len)),
            ByteEdit::Smear(i, n) => {
                let start = i.index(len);
                for b in bytes.iter_mut().skip(start).take(*n as usize) {
                    *b = 0xff;
                }
            }
        }
    }
}

/// Damage to one field of a valid batch's wire message, and the field names its error may give.
#[derive(Clone, Debug)]
enum FieldDamage {
    Count(u32),
    ObsLen(u32),
    ActionDim(u32),
    /// All three shape fields huge at once (the products overflow 64 bits when doubled).
    AllHuge,
    JobIdZero,
    ShortObs(Index),
    LongNextObs(u8),
    ShortActions,
    LongRewards,
    ShortTerminals,
    LongMapIds,
    BadTerminal(Index, u8),
    NanObs(Index),
    NanAction(Index),
    InfReward(Index),
    BadEpisodeFraction(u8, f32),
}

fn huge_or_other() -> impl Strategy<Value = u32> {
    prop_oneof![
        Just(0u32),
        Just(u32::MAX),
        Just(u32::MAX - 1),
        Just(1 << 31),
        0u32..64,
        any::<u32>()
    ]
}

fn field_damage() -> impl Strategy<Value = FieldDamage> {
    prop_oneof![
        huge_or_other().prop_map(FieldDamage::Count),
        huge_or_other().prop_map(FieldDamage::ObsLen),
        huge_or_other().prop_map(FieldDamage::ActionDim),
        Just(FieldDamage::AllHuge),
        Just(FieldDamage::JobIdZero),
        any::<Index>().prop_map(FieldDamage::ShortObs),
        (1u8..=8).prop_map(FieldDamage::LongNextObs),
        Just(FieldDamage::ShortActions),
        Just(FieldDamage::LongRewards),
        Just(FieldDamage::ShortTerminals),
        Just(FieldDamage::LongMapIds),
        (any::<Index>(), 2u8..).prop_map(|(i, v)| FieldDamage::BadTerminal(i, v)),
        any::<Index>().prop_map(FieldDamage::NanObs),
        any::<Index>().prop_map(FieldDamage::NanAction),
        any::<Index>().prop_map(FieldDamage::InfReward),
        (
            0u8..8,
            prop_oneof![
                Just(f32::NAN),
                Just(f32::INFINITY),
                Just(-0.5f32),
                Just(2.0f32),
                Just(f32::MAX)
            ]
        )
            .prop_map(|(k, v)| FieldDamage::BadEpisodeFraction(k, v)),
    ]
}

/// Applies the damage; `None` when it changes nothing (a shape field set to its own value).
fn damage(m: &mut pb::TransitionBatch, d: &FieldDamage) -> Option<&'static [&'static str]> {
    Some(match d {
        FieldDamage::Count(v) if *v != m.count => {
            m.count = *v;
            // The observation bytes are checked first, so a wrong count shows there.
            &["obs_f16", "count"]
        }
        FieldDamage::ObsLen(v) if *v != m.obs_len => {
            m.obs_len = *v;
            &["obs_f16", "obs_len", "count"]
        }
        FieldDamage::ActionDim(v) if *v != m.action_dim => {
            m.action_dim = *v;
            &["actions", "action_dim"]
        }
        FieldDamage::Count(_) | FieldDamage::ObsLen(_) | FieldDamage::ActionDim(_) => return None,
        FieldDamage::AllHuge => {
            (m.count, m.obs_len, m.action_dim) = (u32::MAX, u32::MAX, u32::MAX);
            &["obs_f16", "count"]
        }
        FieldDamage::JobIdZero => {
            m.job_id = 0;
            &["job_id"]
        }
        FieldDamage::ShortObs(i) => {
            let len = m.obs_f16.len();
            m.obs_f16.truncate(i.index(len));
            &["obs_f16"]
        }
        FieldDamage::LongNextObs(n) => {
            m.next_obs_f16.extend(std::iter::repeat_n(0u8, *n as usize));
            &["next_obs_f16"]
        }
        FieldDamage::ShortActions => {
            m.actions.pop();
            &["actions"]
        }
        FieldDamage::LongRewards => {
            m.rewards.push(0.0);
            &["rewards"]
        }
        FieldDamage::ShortTerminals => {
            m.terminals.pop();
            &["terminals"]
        }
        FieldDamage::LongMapIds => {
            m.map_ids.push(0);
            &["map_ids"]
        }
        FieldDamage::BadTerminal(i, v) => {
            let len = m.terminals.len();
            m.terminals[i.index(len)] = *v;
            &["terminals"]
        }
        FieldDamage::NanObs(i) => {
            let k = i.index(m.next_obs_f16.len() / 2) * 2;
            m.next_obs_f16[k..k + 2].copy_from_slice(&f16::NAN.to_bits().to_le_bytes());
            &["next_obs_f16"]
        }
        FieldDamage::NanAction(i) => {
            let len = m.actions.len();
            m.actions[i.index(len)] = f32::NAN;
            &["actions"]
        }
        FieldDamage::InfReward(i) => {
            let len = m.rewards.len();
            m.rewards[i.index(len)] = f32::NEG_INFINITY;
            &["rewards"]
        }
        FieldDamage::BadEpisodeFraction(k, v) => {
            let e = match m.episodes.first_mut() {
                Some(e) => e,
                None => {
                    m.episodes.push(pb::EpisodeResult::default());
                    &mut m.episodes[0]
                }
            };
            let slot = match k {
                0 => &mut e.success,
                1 => &mut e.safety,
                2 => &mut e.speed,
                3 => &mut e.collision,
                4 => &mut e.off_road,
                5 => &mut e.off_route,
                6 => &mut e.wrong_lane,
                _ => &mut e.timeout,
            };
            *slot = *v;
            &["episodes."]
        }
    })
}

proptest! {
    #![proptest_config(config(1024))]

    /// Random bytes: whatever prost decodes converts to a value or to an error naming a field.
    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..512)) {
        decode_all(&bytes)?;
    }

    /// A valid batch round-trips; byte edits of its encoding decode and convert without a panic.
    #[test]
    fn mutated_batches_never_panic(b in valid_batch(), edits in prop::collection::vec(byte_edit(), 1..8)) {
        let mut bytes = sf_proto::batch_to_wire(&b).encode_to_vec();
        let back = sf_proto::batch_from_wire(pb::TransitionBatch::decode(bytes.as_slice()).expect("a valid encoding decodes"));
        prop_assert_eq!(back, Ok(b));
        apply(&mut bytes, &edits);
        decode_all(&bytes)?;
    }

    /// A valid assignment round-trips; byte edits of its encoding never panic.
    #[test]
    fn mutated_assignments_never_panic(a in valid_assignment(), edits in prop::collection::vec(byte_edit(), 1..8)) {
        let mut bytes = sf_proto::assignment_to_wire(&a).encode_to_vec();
        let back = sf_proto::assignment_from_wire(&pb::Assignment::decode(bytes.as_slice()).expect("a valid encoding decodes"));
        prop_assert_eq!(back, Ok(a));
        apply(&mut bytes, &edits);
        decode_all(&bytes)?;
    }

    /// A valid evaluation cell round-trips; byte edits of its encoding never panic.
    #[test]
    fn mutated_eval_work_never_panics(w in valid_eval_work(), edits in prop::collection::vec(byte_edit(), 1..8)) {
        let mut bytes = sf_proto::eval_work_to_wire(&w).encode_to_vec();
        let back = sf_proto::eval_work_from_wire(&pb::EvalAssignment::decode(bytes.as_slice()).expect("a valid encoding decodes"));
        prop_assert_eq!(back, Ok(w));
        apply(&mut bytes, &edits);
        decode_all(&bytes)?;
    }

    /// Valid evaluation results convert episode by episode; byte edits never panic.
    #[test]
    fn mutated_eval_results_never_panic(r in valid_eval_results(), edits in prop::collection::vec(byte_edit(), 1..8)) {
        let mut bytes = r.encode_to_vec();
        let back = pb::EvalResults::decode(bytes.as_slice()).expect("a valid encoding decodes");
        for e in &back.episodes {
            prop_assert!(sf_proto::eval_episode_from_wire(e).is_ok(), "{:?}", e);
        }
        apply(&mut bytes, &edits);
        decode_all(&bytes)?;
    }

    /// Shape fields set to other or huge values, arrays a row off, bad flags and non-finite
    /// values: the batch is refused with an error naming the field where the damage shows.
    #[test]
    fn damaged_batch_fields_are_named(b in valid_batch(), d in field_damage()) {
        let mut m = sf_proto::batch_to_wire(&b);
        let Some(fields) = damage(&mut m, &d) else { return Ok(()) };
        let e = sf_proto::batch_from_wire(m).expect_err("a damaged batch is refused");
        let msg = e.to_string();
        prop_assert!(fields.iter().any(|f| msg.contains(f)), "{:?}: `{}` names none of {:?}", d, msg, fields);
        named(Err(e))?;
    }

    /// Ids, versions and counters at their extremes are plain values, not errors.
    #[test]
    fn extreme_counters_still_decode(b in valid_batch(), job_id in prop_oneof![Just(u64::MAX), 1u64..], worker_id in prop_oneof![Just(u64::MAX), any::<u64>()]) {
        let mut m = sf_proto::batch_to_wire(&b);
        (m.job_id, m.worker_id, m.policy_version, m.sim_steps) = (job_id, worker_id, u64::MAX, u64::MAX);
        let back = sf_proto::batch_from_wire(m).expect("extreme counters are valid");
        prop_assert_eq!((back.job_id.get(), back.worker_id.get(), back.acted_by.version().map(|v| v.get()), back.sim_steps), (job_id, worker_id, Some(u64::MAX), u64::MAX));
    }
}
