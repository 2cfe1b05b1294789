//! The forward pass and its gradient for every variant: finite differences, AVX2 vs portable
//! kernels, batching, and caller mistakes as errors. (Against the trainer's candle model and the
//! numpy reference: trainer/tests and tests/verifier_parity.rs.)

use verifier::kernels::Isa;
use verifier::testutil::RandomSpec;
use verifier::{Kind, Variant, Verifier, VerifierError};

struct Lcg(u64);
impl Lcg {
    fn vec(&mut self, n: usize, s: f32) -> Vec<f32> {
        (0..n)
            .map(|_| {
                self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((self.0 >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * s
            })
            .collect()
    }
}

fn close(a: &[f32], b: &[f32], tol: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol * y.abs().max(1.0), "{what}[{i}]: {x} vs {y}");
    }
}

/// Every shape the contract allows: lowdim, odd widths, a deep Q trunk, features with and
/// without encoder LayerNorm, extra inputs, standardised (older) action inputs.
fn specs() -> Vec<(&'static str, RandomSpec)> {
    let odd = RandomSpec {
        obs_keys: vec![("a".into(), 3), ("b".into(), 4)],
        obs_history: 1,
        chunk_len: 3,
        action_dim: 5,
        encoder_width: 20,
        t_embed_dim: 6,
        trunk_dims: vec![30, 12],
        ..RandomSpec::square()
    };
    vec![
        ("square", RandomSpec::square()),
        ("nav", RandomSpec::nav()),
        ("odd", odd),
        ("deep q", RandomSpec { kind: Kind::Q, trunk_dims: vec![40, 24, 9], ..RandomSpec::nav() }),
        ("one-layer trunk", RandomSpec { trunk_dims: vec![24], ..RandomSpec::nav() }),
        ("standardized", RandomSpec { standardized: true, ..RandomSpec::nav() }),
        (
            "features + extras",
            RandomSpec {
                extra_inputs: vec![("lang".into(), 5, 4), ("proprio".into(), 3, 6)],
                ..RandomSpec::nav_features()
            },
        ),
        (
            "features q, input LN only",
            RandomSpec { kind: Kind::Q, encoder_layernorm: false, ..RandomSpec::nav_features() },
        ),
        (
            "features, no LN, odd widths",
            RandomSpec {
                input_layernorm: false,
                encoder_layernorm: false,
                encoder_width: 13,
                trunk_dims: vec![19, 11],
                ..RandomSpec::nav_features()
            },
        ),
    ]
}

fn extras_for(v: &Verifier, b: usize, rng: &mut Lcg) -> Vec<Vec<f32>> {
    v.extra_inputs().iter().map(|(_, d)| rng.vec(b * d, 1.0)).collect()
}

#[test]
fn gradients_match_finite_differences_for_every_variant() {
    let mut rng = Lcg(1);
    for (i, (name, spec)) in specs().into_iter().enumerate() {
        let (cfg, w) = spec.build(i as u64);
        for isa in [Isa::detect(), Isa::Portable] {
            let v = Verifier::with_isa(cfg.clone(), &w, isa).unwrap();
            let obs = rng.vec(2 * v.obs_dim(), 1.5);
            let chunks = rng.vec(2 * v.act_dim(), 1.5);
            let ex = extras_for(&v, 2, &mut rng);
            let exr: Vec<&[f32]> = ex.iter().map(|e| e.as_slice()).collect();
            let t = [3u32, 40];
            let g = v.grad_ext(&obs, &exr, &t, &chunks).unwrap();
            assert!(g.iter().any(|x| x.abs() > 1e-4), "{name}: gradient is trivially zero");
            // Objective of row 1 alone: log C (classifier) or Q.
            let f = |c: &[f32]| -> f64 {
                let s = v.score_ext(&obs, &exr, &t, c, 1).unwrap()[1] as f64;
                if spec.kind == Kind::Q {
                    s
                } else {
                    s.ln()
                }
            };
            let ad = v.act_dim();
            for j in 0..ad {
                let got = g[ad + j] as f64;
                // Central differences at two step sizes: a ReLU kink inside one step spoils that
                // one only (f32 scores limit how small the step can be).
                let err = [1e-2f32, 2.5e-3]
                    .iter()
                    .map(|&h| {
                        let (mut p, mut m) = (chunks.clone(), chunks.clone());
                        p[ad + j] += h;
                        m[ad + j] -= h;
                        let fd = (f(&p) - f(&m)) / (2.0 * h as f64);
                        (fd - got).abs() - 2e-2 * fd.abs()
                    })
                    .fold(f64::INFINITY, f64::min);
                assert!(err < 2e-3, "{name} ({isa:?}) d/da[{j}]: {got} off finite differences by {err}");
            }
        }
    }
}

#[test]
fn avx2_and_portable_kernels_agree_on_scores_and_gradients() {
    let mut rng = Lcg(2);
    for (i, (name, spec)) in specs().into_iter().enumerate() {
        let (cfg, w) = spec.build(100 + i as u64);
        let fast = Verifier::new(cfg.clone(), &w).unwrap();
        let port = Verifier::with_isa(cfg, &w, Isa::Portable).unwrap();
        assert_eq!(port.backend_name(), "portable");
        for &(b, n) in &[(1usize, 10usize), (3, 5), (2, 1), (5, 3)] {
            let obs = rng.vec(b * fast.obs_dim(), 2.0);
            let t: Vec<u32> = (0..b as u32).map(|i| 7 + 13 * i).collect();
            let cands = rng.vec(b * n * fast.act_dim(), 2.0);
            let ex = extras_for(&fast, b, &mut rng);
            let exr: Vec<&[f32]> = ex.iter().map(|e| e.as_slice()).collect();
            let sf = fast.score_ext(&obs, &exr, &t, &cands, n).unwrap();
            let sp = port.score_ext(&obs, &exr, &t, &cands, n).unwrap();
            close(&sf, &sp, 1e-5, &format!("{name} score b={b} n={n}"));
            let chunks = &cands[..b * fast.act_dim()];
            let gf = fast.grad_ext(&obs, &exr, &t, chunks).unwrap();
            let gp = port.grad_ext(&obs, &exr, &t, chunks).unwrap();
            close(&gf, &gp, 1e-5, &format!("{name} grad b={b}"));
        }
    }
}

#[test]
fn a_batch_gives_what_each_row_gives_alone() {
    let mut rng = Lcg(3);
    for (i, (name, spec)) in specs().into_iter().enumerate() {
        let (cfg, w) = spec.build(200 + i as u64);
        let v = Verifier::new(cfg, &w).unwrap();
        let (b, n, od, ad) = (4, 3, v.obs_dim(), v.act_dim());
        let obs = rng.vec(b * od, 1.0);
        let t = [0u32, 5, 99, 1234];
        let cands = rng.vec(b * n * ad, 1.0);
        let ex = extras_for(&v, b, &mut rng);
        let exr: Vec<&[f32]> = ex.iter().map(|e| e.as_slice()).collect();
        let all = v.score_ext(&obs, &exr, &t, &cands, n).unwrap();
        let grads = v.grad_ext(&obs, &exr, &t, &cands[..b * ad]).unwrap();
        for g in 0..b {
            let row_ex: Vec<Vec<f32>> =
                ex.iter().zip(v.extra_inputs()).map(|(e, (_, d))| e[g * d..(g + 1) * d].to_vec()).collect();
            let rr: Vec<&[f32]> = row_ex.iter().map(|e| e.as_slice()).collect();
            let one = v
                .score_ext(
                    &obs[g * od..(g + 1) * od],
                    &rr,
                    &t[g..g + 1],
                    &cands[g * n * ad..(g + 1) * n * ad],
                    n,
                )
                .unwrap();
            close(&all[g * n..(g + 1) * n], &one, 1e-6, &format!("{name} group {g}"));
            let gone = v
                .grad_ext(&obs[g * od..(g + 1) * od], &rr, &t[g..g + 1], &cands[g * ad..(g + 1) * ad])
                .unwrap();
            close(&grads[g * ad..(g + 1) * ad], &gone, 1e-6, &format!("{name} grad row {g}"));
        }
        // The classifier's score is a probability; the gradient of log C is finite.
        if v.kind() == Kind::Classifier {
            assert!(all.iter().all(|s| (0.0..=1.0).contains(s)), "{name}");
        }
        assert!(grads.iter().all(|g| g.is_finite()), "{name}");
    }
}

#[test]
fn caller_mistakes_are_errors_not_panics() {
    let (cfg, w) =
        RandomSpec { extra_inputs: vec![("lang".into(), 5, 4)], ..RandomSpec::nav_features() }.build(9);
    let v = Verifier::new(cfg, &w).unwrap();
    let (od, ad) = (v.obs_dim(), v.act_dim());
    let obs = vec![0.1; 2 * od];
    let lang = vec![0.2; 2 * 5];
    let ex: [&[f32]; 1] = [&lang];
    let c = vec![0.3; 2 * 3 * ad];
    assert_eq!(v.score_ext(&obs, &ex, &[1, 2], &c, 3).unwrap().len(), 6);
    let input_err = |r: verifier::Result<Vec<f32>>| matches!(r, Err(VerifierError::Input(_)));
    assert!(input_err(v.score_ext(&obs[..od], &ex, &[1, 2], &c, 3)), "short obs");
    assert!(input_err(v.score_ext(&obs, &ex, &[1, 2], &c[..c.len() - 1], 3)), "short candidates");
    assert!(input_err(v.score_ext(&obs, &[], &[1, 2], &c, 3)), "missing extra input");
    assert!(input_err(v.score_ext(&obs, &[&lang[..5]], &[1, 2], &c, 3)), "short extra input");
    assert!(input_err(v.score_ext(&obs, &ex, &[1, 2], &c, usize::MAX)), "n overflows");
    assert!(input_err(v.grad_ext(&obs, &ex, &[1, 2], &c)), "grad takes one chunk per row");
    let mut small = vec![0.0; 5];
    assert!(matches!(v.score_into(&obs, &ex, &[1, 2], &c, 3, &mut small), Err(VerifierError::Input(_))));
    assert!(matches!(
        v.grad_into(&obs, &ex, &[1, 2], &c[..2 * ad], &mut small),
        Err(VerifierError::Input(_))
    ));
    // n = 0 and an empty batch are fine: nothing to score.
    assert_eq!(v.score_ext(&obs, &ex, &[1, 2], &[], 0).unwrap(), Vec::<f32>::new());
    assert_eq!(v.score_ext(&[], &[&[]], &[], &[], 10).unwrap(), Vec::<f32>::new());
    assert_eq!(v.grad_ext(&[], &[&[]], &[], &[]).unwrap(), Vec::<f32>::new());
    // NaN in, NaN out (no panic).
    let mut nan_obs = obs.clone();
    nan_obs[0] = f32::NAN;
    assert!(v.score_ext(&nan_obs, &ex, &[1, 2], &c, 3).unwrap()[0].is_nan());
}

#[test]
fn verifier_is_send_and_sync_and_scores_from_threads() {
    let (cfg, w) = RandomSpec::nav().build(4);
    let v = std::sync::Arc::new(Verifier::new(cfg, &w).unwrap());
    let obs = vec![0.25; v.obs_dim()];
    let c = vec![0.5; 4 * v.act_dim()];
    let want = v.score(&obs, &[3], &c, 4).unwrap();
    let handles: Vec<_> = (0..4)
        .map(|_| {
            let (v, obs, c) = (v.clone(), obs.clone(), c.clone());
            std::thread::spawn(move || v.score(&obs, &[3], &c, 4).unwrap())
        })
        .collect();
    for h in handles {
        assert_eq!(h.join().unwrap(), want);
    }
}

#[test]
fn standardized_artifacts_standardize_and_policy_space_ones_do_not() {
    // The same weights read as a policy-space artifact (act_mean 0, act_std 1) and as an older
    // standardised one: the standardised one equals the policy-space one on (c - mean) / std.
    let (cfg, w) = RandomSpec { standardized: true, ..RandomSpec::nav() }.build(5);
    let std_v = Verifier::new(cfg.clone(), &w).unwrap();
    assert!(!std_v.takes_policy_space());
    let mut pol = cfg.clone();
    pol.input.act_mean = vec![0.0; pol.input.act_dim];
    pol.input.act_std = vec![1.0; pol.input.act_dim];
    pol.input.action_space = verifier::ActionSpace::default();
    let pol_v = Verifier::new(pol, &w).unwrap();
    assert!(pol_v.takes_policy_space());
    let obs = vec![0.3; std_v.obs_dim()];
    let raw: Vec<f32> = (0..std_v.act_dim()).map(|i| (i as f32 * 0.7).sin()).collect();
    let standardized: Vec<f32> =
        raw.iter().enumerate().map(|(i, r)| (r - cfg.input.act_mean[i]) / cfg.input.act_std[i]).collect();
    close(
        &std_v.score(&obs, &[2], &raw, 1).unwrap(),
        &pol_v.score(&obs, &[2], &standardized, 1).unwrap(),
        1e-5,
        "score",
    );
    // Chain rule: d/d raw = d/d standardized / std.
    let g_raw = std_v.grad(&obs, &[2], &raw).unwrap();
    let g_std: Vec<f32> = pol_v
        .grad(&obs, &[2], &standardized)
        .unwrap()
        .iter()
        .enumerate()
        .map(|(i, g)| g / cfg.input.act_std[i])
        .collect();
    close(&g_raw, &g_std, 1e-5, "grad");
    let _ = Variant::Lowdim;
}
