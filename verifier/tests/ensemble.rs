//! Ensemble artifacts: the members' mean and spread against each member run as an artifact of
//! its own, best-of-N's pessimistic pick and its fall-back, guidance scaled by the members'
//! agreement, the file round trip, and what a client must refuse.

use verifier::ensemble::{agree_gradients, argmax, mean_spread, pick_group};
use verifier::testutil::RandomSpec;
use verifier::{
    member_prefix, ArtifactFiles, EnsembleSpec, Kind, Verifier, VerifierError, Weights, SCHEMA_VERSION,
};

fn lcg(seed: u64, n: usize, s: f32) -> Vec<f32> {
    let mut x = seed;
    (0..n)
        .map(|_| {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * s
        })
        .collect()
}

/// Member `k` of an ensemble as a verifier of its own (its tensors unprefixed).
fn member(cfg: &verifier::ArtifactConfig, w: &Weights, k: usize) -> Verifier {
    let mut one = cfg.clone();
    one.schema_version = SCHEMA_VERSION;
    one.ensemble = None;
    let p = member_prefix(k);
    let mut mw = Weights::default();
    for (name, t) in w.iter() {
        if let Some(rest) = name.strip_prefix(&p) {
            mw.insert(rest, t.shape.clone(), t.data.clone()).unwrap();
        }
    }
    Verifier::new(one, &mw).unwrap()
}

#[test]
fn an_ensemble_scores_the_members_mean_with_their_spread() {
    for (kind, spec) in [
        (Kind::Classifier, RandomSpec::nav()),
        (Kind::Q, RandomSpec { kind: Kind::Q, ..RandomSpec::nav_features() }),
    ] {
        let (cfg, w) = spec.build_ensemble(11, 5);
        let v = Verifier::new(cfg.clone(), &w).unwrap();
        assert_eq!((v.members(), v.kind()), (5, kind));
        let (b, n) = (3, 7);
        let obs = lcg(1, b * v.obs_dim(), 1.5);
        let cands = lcg(2, b * n * v.act_dim(), 1.0);
        let t = [0u32, 5, 90];
        let mean = v.score(&obs, &t, &cands, n).unwrap();
        let per: Vec<Vec<f32>> =
            (0..5).map(|k| member(&cfg, &w, k).score(&obs, &t, &cands, n).unwrap()).collect();
        let (mut m2, mut s2) = (vec![0f32; b * n], vec![0f32; b * n]);
        v.score_spread_into(&obs, &[], &t, &cands, n, &mut m2, &mut s2).unwrap();
        for i in 0..b * n {
            let (mu, sd) = mean_spread(per.iter().map(|p| p[i]));
            assert_eq!(mean[i], mu, "{kind:?}: the score is the members' mean");
            assert_eq!((m2[i], s2[i]), (mu, sd));
            let direct: f64 = per.iter().map(|p| p[i] as f64).sum::<f64>() / 5.0;
            assert!((mu as f64 - direct).abs() < 1e-6);
            assert!(sd > 0.0, "random members disagree");
        }
        // Member-major member scores.
        let mut all = vec![0f32; 5 * b * n];
        v.score_members_into(&obs, &[], &t, &cands, n, &mut all).unwrap();
        for k in 0..5 {
            assert_eq!(&all[k * b * n..(k + 1) * b * n], per[k].as_slice());
        }
    }
}

#[test]
fn best_of_n_falls_back_to_the_policys_own_chunk_when_members_disagree() {
    let spec = EnsembleSpec::new(5);
    // 5 members x 3 candidates: candidate 2 has the best mean, 4 of 5 members prefer it to 0.
    #[rustfmt::skip]
    let agree = [
        0.5, 0.1, 0.9,
        0.5, 0.1, 0.8,
        0.5, 0.1, 0.7,
        0.5, 0.1, 0.9,
        0.5, 0.1, 0.4,
    ];
    assert_eq!(pick_group(&agree, 3, &spec), (2, false, 0.8));
    // Candidate 2 is still the pessimistic pick, but only 3 of 5 members score it above
    // candidate 0: the policy's own first chunk is kept.
    #[rustfmt::skip]
    let split = [
        0.5, 0.1, 0.9,
        0.5, 0.1, 0.9,
        0.5, 0.1, 0.9,
        0.7, 0.1, 0.65,
        0.7, 0.1, 0.65,
    ];
    let (i, fell_back, a) = pick_group(&split, 3, &spec);
    assert_eq!((i, fell_back), (0, true));
    assert!((a - 0.6).abs() < 1e-6);
    // Pessimism: candidate 1 has the higher mean but a large spread; κ = 1 prefers candidate 2.
    #[rustfmt::skip]
    let risky = [
        0.0, 1.0, 0.6,
        0.0, 0.1, 0.6,
        0.0, 1.0, 0.6,
        0.0, 0.1, 0.6,
        0.0, 1.0, 0.6,
    ];
    assert_eq!(pick_group(&risky, 3, &spec).0, 2);
    let greedy = EnsembleSpec { pessimism: 0.0, ..spec.clone() };
    assert_eq!(pick_group(&risky, 3, &greedy).0, 1);
    // The pick is the first candidate: nothing to overrule.
    assert_eq!(pick_group(&[0.9, 0.1, 0.8, 0.2], 2, &EnsembleSpec::new(2)), (0, false, 1.0));
    assert_eq!(argmax(&[f32::NAN, 0.1, 0.1]), 1);
}

#[test]
fn picks_of_a_loaded_ensemble_follow_the_rule_and_one_network_picks_the_argmax() {
    let (cfg, w) = RandomSpec::nav().build_ensemble(3, 5);
    let v = Verifier::new(cfg.clone(), &w).unwrap();
    let (b, n) = (16, 30);
    let obs = lcg(4, b * v.obs_dim(), 1.0);
    let cands = lcg(5, b * n * v.act_dim(), 1.0);
    let t: Vec<u32> = (0..b as u32).map(|i| i * 3).collect();
    let p = v.pick(&obs, &[], &t, &cands, n).unwrap();
    let mut all = vec![0f32; 5 * b * n];
    v.score_members_into(&obs, &[], &t, &cands, n, &mut all).unwrap();
    let spec = cfg.ensemble.clone().unwrap();
    let mut fell = 0;
    for g in 0..b {
        let group: Vec<f32> =
            (0..5).flat_map(|k| all[k * b * n + g * n..k * b * n + (g + 1) * n].to_vec()).collect();
        let (i, f, a) = pick_group(&group, n, &spec);
        assert_eq!((p.index[g], p.fell_back[g], p.agreement[g]), (i, f, a), "group {g}");
        fell += f as usize;
    }
    assert_eq!(p.scores, v.score(&obs, &t, &cands, n).unwrap());
    eprintln!("random members: {fell} of {b} groups fell back");
    assert!(fell > 0, "random members disagree on some picks");

    let (one_cfg, one_w) = RandomSpec::nav().build(3);
    let one = Verifier::new(one_cfg, &one_w).unwrap();
    let p = one.pick(&obs, &[], &t, &cands, n).unwrap();
    let s = one.score(&obs, &t, &cands, n).unwrap();
    for g in 0..b {
        assert_eq!(p.index[g], argmax(&s[g * n..(g + 1) * n]));
    }
    assert!(p.fell_back.iter().all(|f| !f) && p.spread.iter().all(|&x| x == 0.0));
    assert!(matches!(one.pick(&obs, &[], &t, &[], 0), Err(VerifierError::Input(_))));
}

#[test]
fn guidance_pushes_only_as_far_as_the_members_agree() {
    let spec = EnsembleSpec::new(3);
    let mut out = vec![0f32; 2];
    // The same direction: R = 1, the full mean.
    let r = agree_gradients(&[1.0, 0.0, 2.0, 0.0, 3.0, 0.0], 2, &spec, &mut out);
    assert!((r - 1.0).abs() < 1e-6 && (out[0] - 2.0).abs() < 1e-6 && out[1] == 0.0);
    // Opposed members: R = 0 and no push.
    let r = agree_gradients(&[1.0, 0.0, -1.0, 0.0, 0.0, 1.0], 2, &spec, &mut out);
    assert!(r < 0.5 && out == [0.0, 0.0], "{r} {out:?}");
    // Partly agreeing: R between r0 and 1 scales the mean by (R − r0) / (1 − r0).
    let g = [1.0, 0.0, 0.0, 1.0, 1.0, 0.0];
    let r = agree_gradients(&g, 2, &spec, &mut out);
    let mean: [f32; 2] = [2.0 / 3.0, 1.0 / 3.0];
    let want_r: f32 = (mean[0] * mean[0] + mean[1] * mean[1]).sqrt();
    assert!((r - want_r).abs() < 1e-6);
    let scale = (want_r - 0.5) / 0.5;
    assert!((out[0] - mean[0] * scale).abs() < 1e-6 && (out[1] - mean[1] * scale).abs() < 1e-6);

    // A loaded ensemble's gradient is that rule over its members' gradients.
    let (cfg, w) = RandomSpec::nav().build_ensemble(8, 4);
    let v = Verifier::new(cfg.clone(), &w).unwrap();
    let b = 5;
    let obs = lcg(6, b * v.obs_dim(), 1.0);
    let chunks = lcg(7, b * v.act_dim(), 1.0);
    let t = [1u32, 2, 3, 4, 5];
    let g = v.grad(&obs, &t, &chunks).unwrap();
    let d = v.act_dim();
    let per: Vec<Vec<f32>> = (0..4).map(|k| member(&cfg, &w, k).grad(&obs, &t, &chunks).unwrap()).collect();
    let mut agreement = vec![0f32; b];
    let mut g2 = vec![0f32; b * d];
    v.grad_agreement_into(&obs, &[], &t, &chunks, &mut g2, &mut agreement).unwrap();
    assert_eq!(g, g2);
    for r in 0..b {
        let row: Vec<f32> = per.iter().flat_map(|p| p[r * d..(r + 1) * d].to_vec()).collect();
        let mut want = vec![0f32; d];
        let ra = agree_gradients(&row, d, cfg.ensemble.as_ref().unwrap(), &mut want);
        assert_eq!(&g[r * d..(r + 1) * d], want.as_slice());
        assert_eq!(agreement[r], ra);
    }
}

#[test]
fn an_ensemble_artifact_round_trips_and_is_refused_where_it_is_not_whole() {
    let (cfg, w) = RandomSpec::nav().build_ensemble(21, 3);
    let files = ArtifactFiles::build(&cfg, &w).unwrap();
    let manifest: serde_json::Value = serde_json::from_slice(&files.manifest).unwrap();
    assert_eq!(manifest["schema_version"], 2, "an ensemble's manifest says so to every client");
    let dir = tempfile::tempdir().unwrap();
    files.write_dir(dir.path()).unwrap();
    let v = Verifier::load_dir(dir.path()).unwrap();
    assert_eq!((v.members(), v.id()), (3, Some(files.id.as_str())));
    let direct = Verifier::new(cfg.clone(), &w).unwrap();
    let obs = lcg(1, v.obs_dim(), 1.0);
    let c = lcg(2, 4 * v.act_dim(), 1.0);
    assert_eq!(v.score(&obs, &[3], &c, 4).unwrap(), direct.score(&obs, &[3], &c, 4).unwrap());

    // A member missing, or one too many: refused, never scored with what is there.
    let mut short = w.clone();
    short.remove("members.2.head.bias");
    assert!(matches!(Verifier::new(cfg.clone(), &short), Err(VerifierError::MissingTensor { .. })));
    let (_, w4) = RandomSpec::nav().build_ensemble(21, 4);
    assert!(matches!(Verifier::new(cfg.clone(), &w4), Err(VerifierError::UnexpectedTensor { .. })));
    // The schema and the ensemble block go together, both ways.
    let mut no_block = cfg.clone();
    no_block.ensemble = None;
    assert!(Verifier::new(no_block, &w).unwrap_err().to_string().contains("no `ensemble`"));
    let mut v1 = cfg.clone();
    v1.schema_version = SCHEMA_VERSION;
    assert!(Verifier::new(v1, &w).unwrap_err().to_string().contains("needs schema_version 2"));
    for bad in [
        EnsembleSpec { members: 1, ..EnsembleSpec::new(3) },
        EnsembleSpec { pessimism: -1.0, ..EnsembleSpec::new(3) },
        EnsembleSpec { min_agreement: 1.0, ..EnsembleSpec::new(3) },
    ] {
        let c = verifier::ArtifactConfig { ensemble: Some(bad), ..cfg.clone() };
        assert!(matches!(Verifier::new(c, &w), Err(VerifierError::Config(_))));
    }
    // A manifest whose schema differs from its config's: refused (an old writer's manifest
    // cannot smuggle an ensemble past a check).
    let m = String::from_utf8(files.manifest.clone())
        .unwrap()
        .replace("\"schema_version\": 2", "\"schema_version\": 1");
    std::fs::write(dir.path().join("manifest.json"), m).unwrap();
    let e = Verifier::load_dir(dir.path()).unwrap_err().to_string();
    assert!(e.contains("schema_version 1, config.json 2"), "{e}");
    // An unknown block field is refused: it could change the rules.
    let mut j: serde_json::Value = serde_json::from_slice(&files.config).unwrap();
    j["ensemble"]["temperature"] = 2.0.into();
    assert!(verifier::ArtifactConfig::from_json(&serde_json::to_vec(&j).unwrap()).is_err());
}
