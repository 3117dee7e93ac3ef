//! The job config's tests: defaults, round trips and each section's refusals.

use super::*;

const MIN: &str = "name = \"t\"\n[env]\nscenarios = [\"merge\"]\n[train]\nenv_steps = 1000\n";

#[test]
fn a_minimal_config_gets_the_paper_defaults() {
    let c = JobConfig::from_toml(&format!("{MIN}[sac]\nwarmup_steps = 100\n")).expect("valid");
    assert_eq!(c.sac.gamma, 0.9);
    assert_eq!(c.sac.batch_size, 128);
    assert_eq!(c.net.preset, NetPreset::Fast);
    let again = JobConfig::from_toml(&c.to_toml()).expect("round trip");
    assert_eq!(again, c);
}

/// `env.reward_neighbours`: "observed" on the composed-reward flows; refused, with the
/// field named, where the reward has no neighbour term; absent from a default's TOML.
#[test]
fn reward_neighbours_only_where_the_reward_composes() {
    let with = |kind: &str, v: &str| {
        JobConfig::from_toml(&format!(
            "kind = \"{kind}\"\n{}[sac]\nwarmup_steps = 100\n",
            MIN.replace("[train]", &format!("reward_neighbours = \"{v}\"\n[train]"))
        ))
    };
    let ok = with("socialcomm", "observed").expect("socialcomm observed");
    assert_eq!(ok.env.reward_neighbours, RewardNeighbours::Observed);
    assert_eq!(JobConfig::from_toml(&ok.to_toml()).expect("round trip"), ok);
    assert!(with("copo", "observed").is_ok());
    for kind in ["macad", "ego"] {
        let e = with(kind, "observed").expect_err(kind).to_string();
        assert!(e.contains("env.reward_neighbours") && e.contains(kind), "{e}");
    }
    assert!(with("socialcomm", "nearby").is_err());
    let radius = with("macad", "radius").expect("the default is fine anywhere");
    assert!(!radius.to_toml().contains("reward_neighbours"));
}

/// `env.svo_range_deg`: a flow's or FailMaker's own range, inside [-90, 90], low <= high;
/// refused on ego jobs (whose background brings its own) with the field named.
#[test]
fn svo_range_is_a_flows_and_is_checked() {
    let fm = |r: &str, kind: &str| {
        let ego = if kind.contains("failmaker") { "ego_job = 1\n" } else { "" };
        JobConfig::from_toml(&format!(
            "{kind}{}[sac]\nwarmup_steps = 100\n",
            MIN.replace("[train]", &format!("svo_range_deg = {r}\n{ego}[train]"))
        ))
    };
    let ok = fm("[-90.0, -90.0]", "kind = \"failmaker\"\n").map(|j| j.env.svo_range_deg);
    assert_eq!(ok.ok().flatten(), Some([-90.0, -90.0]));
    assert!(fm("[0.0, 45.0]", "kind = \"copo\"\n").is_ok());
    for (r, kind) in [
        ("[10.0, -10.0]", "kind = \"failmaker\"\n"),
        ("[-100.0, 0.0]", "kind = \"failmaker\"\n"),
        ("[0.0, 90.0]", ""),
    ] {
        let e = fm(r, kind).expect_err(r);
        assert!(e.to_string().contains("env.svo_range_deg"), "{r} {kind}: {e}");
    }
}

#[test]
fn lateral_action_slow_leader_and_policy_warmup_are_checked() {
    let lat = MIN.replace("[train]", "action = \"idm-residual-lateral\"\n[train]");
    let ok = JobConfig::from_toml(&format!(
        "{lat}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_lane_change_prob = 0.05\n"
    ))
    .expect("valid");
    assert_eq!((ok.action_dim(), ok.sac.warmup_lane_change_prob), (2, 0.05));
    assert_eq!(JobConfig::from_toml(&ok.to_toml()).expect("round trip"), ok);
    let accel = MIN.replace("[train]", "action = \"idm-accel-residual\"\n[train]");
    let e = JobConfig::from_toml(&format!("{accel}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_lane_change_prob = 0.05\n")).expect_err("no lateral");
    assert!(
        e.to_string().contains("sac.warmup_lane_change_prob")
            && e.to_string().contains("idm-residual-lateral"),
        "{e}"
    );
    let e = JobConfig::from_toml(&format!(
        "{lat}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_lane_change_prob = 1.5\n"
    ))
    .expect_err("range");
    assert!(e.to_string().contains("sac.warmup_lane_change_prob"), "{e}");
    let slow = |v: &str, kind: &str| {
        JobConfig::from_toml(&format!(
            "{kind}{}[sac]\nwarmup_steps = 100\n",
            MIN.replace("[train]", &format!("slow_leader = {v}\n[train]"))
        ))
    };
    assert_eq!(
        slow("{ share = 1.0, speed_mps = 1.5 }", "")
            .expect("valid")
            .case_draw()
            .slow_leader
            .map(|s| s.speed_mps),
        Some(1.5)
    );
    let e = slow("{ share = 1.0, speed_mps = 9.0 }", "").expect_err("too fast");
    assert!(
        e.to_string().contains("env.slow_leader") && e.to_string().contains("speed_mps"),
        "{e}"
    );
    let e =
        slow("{ share = 1.0, speed_mps = 1.0 }", "kind = \"macad\"\n").expect_err("not an ego job");
    assert!(e.to_string().contains("env.slow_leader"), "{e}");
    let policy = format!("{lat}[sac]\nwarmup_steps = 100\nwarmup_policy = \"policy\"\nbc_weight = 0.4\nbc_target = \"zero\"\nbc_q_filter = true\n");
    let e = JobConfig::from_toml(&policy).expect_err("not a continuation");
    assert!(
        e.to_string().contains("sac.warmup_policy") && e.to_string().contains("init_job"),
        "{e}"
    );
    let cont = JobConfig::from_toml(&policy.replace("[train]\n", "[train]\ninit_job = 1\n"))
        .expect("a continuation warms up with its own policy");
    assert_eq!(cont.sac.warmup_policy, WarmupPolicy::Policy);
    assert!(!cont.train.init_replay, "a continuation starts with an empty replay unless asked");
    let carry = |extra: &str| {
        JobConfig::from_toml(&policy.replace("[train]\n", &format!("[train]\n{extra}")))
    };
    let c = carry("init_job = 1\ninit_replay = true\n").expect("a carried replay");
    assert!(c.train.init_replay);
    for (extra, says) in [
        ("init_replay = true\n", "init_job"),
        ("init_job = 1\ninit_replay = true\npersist_replay = false\n", "persist_replay"),
    ] {
        let e = carry(extra).expect_err(extra);
        assert!(e.to_string().contains("train.init_replay") && e.to_string().contains(says), "{e}");
    }
    let e = JobConfig::from_toml(&format!("{lat}[sac]\nwarmup_steps = 100\n"))
        .expect_err("random warm-up");
    assert!(e.to_string().contains("sac.warmup_policy"), "{e}");
}

#[test]
fn errors_name_the_field() {
    let e = JobConfig::from_toml(&format!("{MIN}[sac]\ngamma = 1.5\n")).expect_err("gamma");
    assert!(e.to_string().contains("sac.gamma"), "{e}");
    let e = JobConfig::from_toml(&format!("{MIN}[sac]\nbogus = 1\n")).expect_err("unknown");
    assert!(e.to_string().contains("bogus"), "{e}");
    let e = JobConfig::from_toml(
        &format!("{MIN}[sac]\nwarmup_steps = 5000\n")
            .replace("env_steps = 1000", "env_steps = 1000\nreplay_capacity = 1000"),
    )
    .expect_err("warm-up");
    assert!(e.to_string().contains("sac.warmup_steps"), "{e}");
    let e = JobConfig::from_toml(&format!("{MIN}[coordinator]\niterations = 2\n"))
        .expect_err("not copo");
    assert!(e.to_string().contains("coordinator"), "{e}");
    let copo = format!("kind = \"copo\"\n{MIN}[sac]\nwarmup_steps = 100\n");
    let e = JobConfig::from_toml(&format!("{copo}[coordinator]\nelite_frac = 0.0\n"))
        .expect_err("elite");
    assert!(e.to_string().contains("coordinator.elite_frac"), "{e}");
    assert_eq!(
        JobConfig::from_toml(&copo).expect("copo").coordinator(),
        Some(CoordinatorSection::default()),
        "copo fits one by default"
    );
    assert_eq!(
        JobConfig::from_toml(&format!("{copo}[coordinator]\niterations = 0\n"))
            .expect("stage 1 only")
            .coordinator(),
        None
    );
}

#[test]
fn the_name_idm_is_reserved_for_the_idm_driver() {
    let e = JobConfig::from_toml(&MIN.replace("name = \"t\"", "name = \"idm\"")).expect_err("idm");
    assert!(e.to_string().contains("name") && e.to_string().contains("reserved"), "{e}");
    let e = JobConfig::from_toml(&MIN.replace("name = \"t\"", "name = \"idm-mobil\""))
        .expect_err("idm-mobil");
    assert!(e.to_string().contains("`idm-mobil` is reserved"), "{e}");
}

#[test]
fn the_actor_rate_ramps_up_from_zero_when_the_sac_phase_starts() {
    let cfg = SacConfig {
        lr_actor: 1e-4,
        bc_updates: 100,
        critic_pretrain_updates: 50,
        lr_actor_ramp_updates: 10,
        ..SacConfig::default()
    };
    // Cloning at the full rate; the actor's first SAC update at a tenth, then up to full.
    assert_eq!(cfg.actor_lr(0), 1e-4);
    assert!((cfg.actor_lr(150) - 1e-5).abs() < 1e-12, "{}", cfg.actor_lr(150));
    assert!((cfg.actor_lr(154) - 5e-5).abs() < 1e-12, "{}", cfg.actor_lr(154));
    assert_eq!(cfg.actor_lr(159), 1e-4);
    assert_eq!(cfg.actor_lr(10_000), 1e-4);
    // With the decay the ramp multiplies the decayed rate.
    let decay = SacConfig { lr_actor_final: Some(0.0), lr_actor_decay_updates: 20, ..cfg.clone() };
    assert!((decay.actor_lr(159) - 1e-4 * 11.0 / 20.0).abs() < 1e-12);
    assert_eq!(decay.actor_lr(170), 0.0);
    let plain = SacConfig { lr_actor_ramp_updates: 0, ..cfg };
    assert_eq!(plain.actor_lr(150), 1e-4);
    let text = JobConfig::from_toml(&format!("{MIN}[sac]\nlr_actor_ramp_updates = 10\n"))
        .expect("set")
        .to_toml();
    assert!(text.contains("lr_actor_ramp_updates = 10"), "{text}");
    assert!(!JobConfig::from_toml(MIN).expect("none").to_toml().contains("lr_actor_ramp"));
}

#[test]
fn held_components_need_the_filter_exist_once_and_round_trip_only_when_set_as_clone_only() {
    let dim = JobConfig::from_toml(MIN).expect("min").action_dim();
    let base = format!("{MIN}[sac]\nbc_target = \"oracle\"\nbc_q_filter = true\n");
    let ok = JobConfig::from_toml(&format!("{base}bc_hold_dims = [{}]\n", dim - 1))
        .expect("the last component");
    assert_eq!(ok.sac.bc_hold_dims, vec![dim - 1]);
    let back = JobConfig::from_toml(&ok.to_toml()).expect("round trip");
    assert_eq!(back.sac.bc_hold_dims, vec![dim - 1]);
    assert!(!JobConfig::from_toml(&base).expect("none").to_toml().contains("bc_hold_dims"));
    let only = JobConfig::from_toml(&format!(
        "{base}bc_hold_dims = [{}]\nbc_hold_clone_only = true\n",
        dim - 1
    ))
    .expect("clone only");
    assert!(only.sac.bc_hold_clone_only);
    assert!(JobConfig::from_toml(&only.to_toml()).expect("round trip").sac.bc_hold_clone_only);
    assert!(!ok.to_toml().contains("bc_hold_clone_only"));
    // Each refusal names the field it refuses and why.
    for (text, field, why) in [
        (format!("{base}bc_hold_dims = [{dim}]\n"), "sac.bc_hold_dims", "does not exist"),
        (format!("{base}bc_hold_dims = [0, 0]\n"), "sac.bc_hold_dims", "twice"),
        (
            format!("{MIN}[sac]\nbc_target = \"oracle\"\nbc_hold_dims = [0]\n"),
            "sac.bc_hold_dims",
            "bc_q_filter = true",
        ),
        (
            format!("{base}bc_hold_clone_only = true\n"),
            "sac.bc_hold_clone_only",
            "sac.bc_hold_dims",
        ),
        (
            format!(
                "{base}bc_hold_dims = [0]\nbc_hold_clone_only = true\nbc_decay_updates = 100\n"
            ),
            "sac.bc_hold_clone_only",
            "sac.bc_decay_updates",
        ),
    ] {
        let e = JobConfig::from_toml(&text).expect_err(why);
        assert!(e.to_string().contains(field) && e.to_string().contains(why), "{e}");
    }
}

#[test]
fn the_conservative_critic_validates_and_round_trips_only_when_set() {
    let base = format!("{MIN}[sac]\n");
    let plain = JobConfig::from_toml(&base).expect("none");
    assert_eq!((plain.sac.cql_weight, plain.sac.cql_samples), (0.0, DEFAULT_CQL_SAMPLES));
    let text = plain.to_toml();
    assert!(!text.contains("cql_"), "absent stays absent: {text}");
    let ok =
        JobConfig::from_toml(&format!("{base}cql_weight = 2.0\ncql_samples = 4\n")).expect("set");
    let back = JobConfig::from_toml(&ok.to_toml()).expect("round trip");
    assert_eq!((back.sac.cql_weight, back.sac.cql_samples), (2.0, 4));
    for (extra, field, needle) in [
        ("cql_weight = -1.0", "sac.cql_weight", "finite and >= 0"),
        ("cql_weight = nan", "sac.cql_weight", "finite and >= 0"),
        ("cql_weight = inf", "sac.cql_weight", "finite and >= 0"),
        ("cql_samples = 0", "sac.cql_samples", "1..=100"),
        ("cql_samples = 101", "sac.cql_samples", "1..=100"),
    ] {
        let e = JobConfig::from_toml(&format!("{base}{extra}\n")).expect_err(extra);
        assert!(e.to_string().contains(field) && e.to_string().contains(needle), "{extra}: {e}");
    }
}

#[test]
fn awac_weights_need_a_positive_lambda_and_the_replayed_actions() {
    let base = format!("{MIN}[sac]\nwarmup_policy = \"idm\"\nbc_weight = 0.4\n");
    let ok = JobConfig::from_toml(&format!("{base}bc_awac_lambda = 1.0\n"))
        .expect("replay target by default");
    assert_eq!(ok.sac.bc_awac_lambda, Some(1.0));
    assert_eq!(
        JobConfig::from_toml(&ok.to_toml()).expect("round trip").sac.bc_awac_lambda,
        Some(1.0)
    );
    assert!(
        !JobConfig::from_toml(&base).expect("none").to_toml().contains("bc_awac_lambda"),
        "absent stays absent"
    );
    for (extra, needle) in [
        ("bc_awac_lambda = 0.0", "finite and positive"),
        ("bc_awac_lambda = -1.0", "finite and positive"),
        ("bc_awac_lambda = nan", "finite and positive"),
        ("bc_awac_lambda = inf", "finite and positive"),
    ] {
        let e = JobConfig::from_toml(&format!("{base}{extra}\n")).expect_err(extra);
        assert!(
            e.to_string().contains("sac.bc_awac_lambda") && e.to_string().contains(needle),
            "{extra}: {e}"
        );
    }
    let e = JobConfig::from_toml(&format!(
        "{MIN}[sac]\nwarmup_policy = \"idm\"\nbc_awac_lambda = 1.0\n"
    ))
    .expect_err("no cloning term");
    assert!(
        e.to_string().contains("sac.bc_awac_lambda") && e.to_string().contains("bc_weight > 0"),
        "{e}"
    );
    let zero = MIN.replace("[train]", "action = \"idm-accel-residual\"\n[train]")
        + "[sac]\nwarmup_policy = \"idm\"\nbc_target = \"zero\"\nbc_awac_lambda = 1.0\n";
    let e = JobConfig::from_toml(&zero).expect_err("zero target");
    assert!(
        e.to_string().contains("sac.bc_awac_lambda") && e.to_string().contains("replay"),
        "{e}"
    );
}

#[test]
fn validation_section_is_checked_and_round_trips() {
    let ego = MIN.replace("name = \"t\"\n", "name = \"t\"\nkind = \"ego\"\n");
    let cfg = JobConfig::from_toml(&format!("{ego}[validation]\nevery_updates = 250\n"))
        .expect("ego with validation");
    assert_eq!(
        cfg.validation,
        Some(ValidationSection { every_updates: 250, ..Default::default() })
    );
    assert_eq!(
        JobConfig::from_toml(&cfg.to_toml()).expect("round trip").validation,
        cfg.validation
    );
    assert_eq!(JobConfig::from_toml(&ego).expect("no section").validation, None);
    for (body, field) in [
        ("every_updates = 0", "validation.every_updates"),
        ("episodes = 0", "validation.episodes"),
        ("envs = 0", "validation.envs"),
        ("shots = 3", "shots"),
    ] {
        let e = JobConfig::from_toml(&format!("{ego}[validation]\n{body}\n")).expect_err(body);
        assert!(e.to_string().contains(field), "{body}: {e}");
    }
    let fm = MIN
        .replace("name = \"t\"\n", "name = \"t\"\nkind = \"failmaker\"\n")
        .replace("[train]", "ego_job = 1\n[train]");
    let e = JobConfig::from_toml(&format!("{fm}[validation]\n")).expect_err("an adversary");
    assert!(e.to_string().contains("validation") && e.to_string().contains("failmaker"), "{e}");
}

#[test]
fn the_idm_warm_up_is_checked() {
    let ok = JobConfig::from_toml(&format!("{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 50\ntarget_entropy = -3.0\n")).expect("valid");
    assert_eq!(
        (ok.sac.warmup_policy, ok.sac.bc_updates, ok.sac.target_entropy),
        (WarmupPolicy::Idm, 50, Some(-3.0))
    );
    let e = JobConfig::from_toml(&format!("{MIN}[sac]\nwarmup_steps = 100\nbc_updates = 50\n"))
        .expect_err("nothing to clone");
    assert!(e.to_string().contains("sac.bc_updates"), "{e}");
}

/// The averaged actor: its rate in (0, 1], acting with it only when there is one, and
/// `act_with_average` written only when set.
#[test]
fn acting_with_the_averaged_actor_needs_an_average() {
    let off =
        JobConfig::from_toml(&format!("{MIN}[sac]\nactor_average_tau = 0.01\n")).expect("valid");
    assert!(
        !off.sac.act_with_average && !off.to_toml().contains("act_with_average"),
        "unset is not written"
    );
    let on = JobConfig::from_toml(&format!(
        "{MIN}[sac]\nactor_average_tau = 0.01\nact_with_average = true\n"
    ))
    .expect("valid");
    assert!(on.sac.act_with_average);
    assert_eq!(JobConfig::from_toml(&on.to_toml()).expect("round trip").sac, on.sac);
    for (body, field) in [
        ("act_with_average = true\n", "sac.act_with_average"),
        ("actor_average_tau = 0.0\n", "sac.actor_average_tau"),
        ("actor_average_tau = 1.5\n", "sac.actor_average_tau"),
    ] {
        let e = JobConfig::from_toml(&format!("{MIN}[sac]\n{body}")).expect_err(body);
        assert!(e.to_string().contains(field), "{body}: {e}");
    }
}

/// `bc_from_warmup` restricts the cloning updates, and only those, to the warm-up's rows;
/// it needs cloning updates towards the replayed actions, and is written only when set.
#[test]
fn cloning_from_the_warmup_only() {
    let sac = "[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 50\n";
    let off = JobConfig::from_toml(&format!("{MIN}{sac}")).expect("valid");
    assert_eq!((off.sac.sample_before(0), off.sac.sample_before(49)), (None, None));
    assert!(!off.to_toml().contains("bc_from_warmup"), "unset is not written");
    let on = JobConfig::from_toml(&format!("{MIN}{sac}bc_from_warmup = true\n")).expect("valid");
    assert_eq!(
        (on.sac.sample_before(0), on.sac.sample_before(49), on.sac.sample_before(50)),
        (Some(100), Some(100), None)
    );
    assert_eq!(JobConfig::from_toml(&on.to_toml()).expect("round trip").sac, on.sac);
    for body in
        ["warmup_steps = 100\nwarmup_policy = \"idm\"\nbc_from_warmup = true\n", "warmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 5\nbc_target = \"zero\"\nbc_from_warmup = true\n"]
    {
        let cfg = if body.contains("zero") { MIN.replace("[train]", "action = \"idm-accel-residual\"\n[train]") } else { MIN.to_string() };
        let e = JobConfig::from_toml(&format!("{cfg}[sac]\n{body}")).expect_err(body);
        assert!(e.to_string().contains("sac.bc_from_warmup"), "{body}: {e}");
    }
    let e = JobConfig::from_toml(&format!(
        "{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_noise = 2.0\n"
    ))
    .expect_err("noise");
    assert!(e.to_string().contains("sac.warmup_noise"), "{e}");
    let adv = "kind = \"socialcomm-adv\"\n".to_string()
        + &MIN.replace("[train]", "ego_job = 1\nbackground_job = 2\n[train]");
    let e =
        JobConfig::from_toml(&format!("{adv}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"))
            .expect_err("adversary");
    assert!(e.to_string().contains("sac.warmup_policy"), "{e}");
    let e = JobConfig::from_toml(&format!(
        "{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"expert\"\n"
    ))
    .expect_err("unknown policy");
    assert!(e.to_string().contains("warmup_policy"), "{e}");
}

/// The acceleration residual, the critic's and the cloning term's options, and the
/// observation caps: accepted when they fit, refused naming the field otherwise.
#[test]
fn the_learning_recipe_is_checked() {
    let env = MIN.replace(
        "[train]",
        "action = \"idm-accel-residual\"\nmax_neighbours = 10\nmax_segments = 48\n[train]",
    );
    let ok = JobConfig::from_toml(&format!(
        "{env}[net]\npose_layers = 2\nego_skip = true\ncritic_layer_norm = true\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\ncritic_loss = \"huber\"\nbc_target = \"zero\"\nbc_q_filter = true\ncritic_pretrain_updates = 10\nshared_encoder = true\n"
    ))
    .expect("valid");
    assert_eq!(
        (ok.action_dim(), ok.env.max_neighbours, ok.sac.critic_loss, ok.sac.bc_target),
        (1, Some(10), CriticLoss::Huber, BcTarget::Zero)
    );
    assert_eq!(JobConfig::from_toml(&ok.to_toml()).expect("round trip"), ok);
    // IDM's recorded labels, Q-filtered, with the direct action: no demonstrator needed.
    let oracle = JobConfig::from_toml(&format!(
        "{MIN}[sac]\nwarmup_steps = 100\nbc_target = \"oracle\"\nbc_q_filter = true\nbc_weight = 1.0\n"
    ))
    .expect("oracle labels");
    assert_eq!((oracle.env.action, oracle.sac.bc_target), (ActionMode::Direct, BcTarget::Oracle));
    assert_eq!(JobConfig::from_toml(&oracle.to_toml()).expect("round trip"), oracle);
    for (text, field) in [
        (format!("{env}[sac]\nwarmup_steps = 100\n"), "sac.warmup_policy"),
        (format!("{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_target = \"zero\"\n"), "sac.bc_target"),
        (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_q_filter = true\n"), "sac.bc_q_filter"),
        (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nhuber_delta = 0.0\n"), "sac.huber_delta"),
        (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nn_step = 0\n"), "sac.n_step"),
        (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nn_step = 17\n"), "sac.n_step"),
        (format!("{env}[net]\npose_layers = 9\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"), "net.pose_layers"),
        (format!("{env}[net]\nlog_std_min = 0.5\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"), "net.log_std_min"),
        (format!("{env}[net]\nlog_std_min = -12.0\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"), "net.log_std_min"),
        (format!("{}[sac]\nwarmup_steps = 100\n", MIN.replace("[train]", "max_segments = 0\n[train]")), "env.max_segments"),
        (format!("{}[sac]\nwarmup_steps = 100\n", MIN.replace("[train]", "action = \"idm-brake\"\n[train]")), "action"),
    ] {
        let e = JobConfig::from_toml(&text).expect_err(field);
        assert!(e.to_string().contains(field), "{field}: {e}");
    }
    let adv = "kind = \"socialcomm-adv\"\n".to_string()
        + &MIN.replace(
            "[train]",
            "ego_job = 1\nbackground_job = 2\naction = \"idm-accel-residual\"\n[train]",
        );
    let e =
        JobConfig::from_toml(&format!("{adv}[sac]\nwarmup_steps = 100\n")).expect_err("adversary");
    assert!(e.to_string().contains("env.action"), "{e}");
}

/// `sac.lr_actor_final`: constant before the actor's SAC phase, linear over the decay,
/// flat after it; both fields or neither, the final rate within (0, lr_actor].
#[test]
fn the_actor_learning_rate_decays_after_cloning_and_pretraining() {
    let sac = "[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 10\ncritic_pretrain_updates = 20\nlr_actor = 1e-4\n";
    let c = JobConfig::from_toml(&format!(
        "{MIN}{sac}lr_actor_final = 2e-5\nlr_actor_decay_updates = 100\n"
    ))
    .expect("valid");
    let lr = |u| c.sac.actor_lr(u);
    assert_eq!((lr(0), lr(30)), (1e-4, 1e-4), "constant through cloning and pre-training");
    assert!((lr(80) - 6e-5).abs() < 1e-12, "half way: {}", lr(80));
    assert!((lr(130) - 2e-5).abs() < 1e-12 && (lr(10_000) - 2e-5).abs() < 1e-12, "flat at the end");
    assert_eq!(JobConfig::from_toml(&c.to_toml()).expect("round trip"), c);
    let plain = JobConfig::from_toml(&format!("{MIN}{sac}")).expect("no decay");
    assert_eq!(plain.sac.actor_lr(5_000), 1e-4);
    for (extra, field) in [
        ("lr_actor_decay_updates = 100\n", "sac.lr_actor_decay_updates"),
        ("lr_actor_final = 2e-5\n", "sac.lr_actor_final"),
        ("lr_actor_final = 2e-4\nlr_actor_decay_updates = 100\n", "sac.lr_actor_final"),
        ("lr_actor_final = 0.0\nlr_actor_decay_updates = 100\n", "sac.lr_actor_final"),
    ] {
        let e = JobConfig::from_toml(&format!("{MIN}{sac}{extra}")).expect_err(field);
        assert!(e.to_string().contains(field), "{extra}: {e}");
    }
}

#[test]
fn dependencies_serve_only_in_roles_their_kind_fits() {
    use JobKind::*;
    assert!(DepRole::Background.accepts(Ego, Failmaker).is_ok());
    assert!(DepRole::Background
        .accepts(Ego, Ego)
        .expect_err("ego")
        .to_string()
        .contains("not a traffic flow"));
    assert!(DepRole::Background
        .accepts(SocialcommAdv, Copo)
        .expect_err("not socialcomm")
        .to_string()
        .contains("SocialComm"));
    assert!(DepRole::Background.accepts(SocialcommAdv, Socialcomm).is_ok());
    assert!(DepRole::Ego.accepts(Failmaker, Macad).is_err());
    assert!(DepRole::Ego.accepts(Failmaker, Ego).is_ok());
    assert!(DepRole::Init.accepts(Ego, Failmaker).is_err());
    assert!(DepRole::Init.accepts(Failmaker, Failmaker).is_ok());
}
