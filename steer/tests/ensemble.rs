//! Steering with an ensemble verifier: best-of-N takes the core's pick (pessimistic, falling
//! back to each group's first candidate where the members disagree) and reports the fall-backs;
//! recorded best-of-N logs that choice; guidance pushes along the core's agreement-scaled gradient.

use steer::{best_of_n, best_of_n_recorded, Scorer, Verifier};
use verifier::testutil::RandomSpec;

fn values(seed: u64, n: usize) -> Vec<f32> {
    let mut x = seed;
    (0..n)
        .map(|_| {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * 0.8
        })
        .collect()
}

#[test]
fn best_of_n_with_an_ensemble_takes_the_core_pick_and_counts_fall_backs() {
    let (cfg, w) = RandomSpec::nav().build_ensemble(5, 5);
    let v = Verifier::new(cfg, &w).unwrap();
    let (b, n) = (24, 30);
    let obs = values(1, b * v.obs_dim());
    let cands = values(2, b * n * v.act_dim());
    let t: Vec<u32> = (0..b as u32).collect();
    let best = best_of_n(&v, &obs, &t, &cands, n).unwrap();
    let want = v.pick(&obs, &[], &t, &cands, n).unwrap();
    assert_eq!(best.index, want.index);
    assert_eq!(best.fell_back, want.fell_back);
    assert_eq!(best.scores, v.score(&obs, &t, &cands, n).unwrap());
    let fell = best.fell_back.iter().filter(|&&f| f).count();
    assert!(fell > 0, "random members disagree on some groups");
    assert!((best.fallback_rate() - fell as f64 / b as f64).abs() < 1e-12);
    let ad = v.act_dim();
    for g in 0..b {
        let i = if best.fell_back[g] { 0 } else { best.index[g] };
        assert_eq!(&best.chunks[g * ad..(g + 1) * ad], &cands[(g * n + i) * ad..(g * n + i + 1) * ad]);
    }
    // The recorded variant logs the same choices (on the half-float grid it scores on).
    let artifact = verifier::ArtifactFiles::build(v.config(), &w).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    artifact.write_dir(tmp.path()).unwrap();
    let loaded = Verifier::load_dir(tmp.path()).unwrap();
    let (rec, log) = best_of_n_recorded(&loaded, None, &obs, &t, &cands, n).unwrap();
    assert_eq!(log.iter().map(|s| s.chosen as usize).collect::<Vec<_>>(), rec.index);

    // One network: the argmax, never a fall-back.
    let (one_cfg, one_w) = RandomSpec::nav().build(5);
    let one = Verifier::new(one_cfg, &one_w).unwrap();
    let b1 = best_of_n(&one, &obs, &t, &cands, n).unwrap();
    assert!(b1.fell_back.iter().all(|f| !f));
    assert_eq!(b1.fallback_rate(), 0.0);
}

#[test]
fn guidance_with_an_ensemble_uses_the_agreement_scaled_gradient() {
    let (cfg, w) = RandomSpec::nav().build_ensemble(9, 4);
    let v = Verifier::new(cfg, &w).unwrap();
    let obs = values(3, 3 * v.obs_dim());
    let chunks = values(4, 3 * v.act_dim());
    let t = [0u32, 4, 8];
    let g = v.grad_batch(&obs, &t, &chunks).unwrap();
    let mut agreement = vec![0f32; 3];
    let mut want = vec![0f32; chunks.len()];
    v.grad_agreement_into(&obs, &[], &t, &chunks, &mut want, &mut agreement).unwrap();
    assert_eq!(g, want);
    assert!(agreement.iter().all(|&r| (0.0..=1.0).contains(&r)));
}
