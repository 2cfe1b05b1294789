//! Loss values against hand-computed cases, host vs candle objective gradients, gradient
//! clipping, AdamW, AUC and Pearson.

use candle_core::{Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use trainer::loss::{
    bce_with_logits, bce_with_logits_scalar, contrastive_hinge, contrastive_pairs, mse, objective,
    objective_host, LossConfig,
};
use trainer::metrics::{pearson, roc_auc};
use trainer::optim::{clip_grad_norm, global_norm, linear_factor, AdamW, AdamWConfig};
use trainer::Kind;

fn t1(v: &[f32]) -> Tensor {
    Tensor::from_slice(v, v.len(), &Device::Cpu).unwrap()
}

#[test]
fn bce_hand_computed_including_large_logits() {
    let ln2 = std::f32::consts::LN_2;
    assert!((bce_with_logits_scalar(0.0, 1.0) - ln2).abs() < 1e-7);
    assert!((bce_with_logits_scalar(0.0, 0.0) - ln2).abs() < 1e-7);
    assert!((bce_with_logits_scalar(50.0, 0.0) - 50.0).abs() < 1e-5);
    assert!((bce_with_logits_scalar(-50.0, 1.0) - 50.0).abs() < 1e-5);
    assert!(bce_with_logits_scalar(50.0, 1.0).abs() < 1e-20);
    // log(1 + e^-2) for x = 2, y = 1.
    assert!((bce_with_logits_scalar(2.0, 1.0) - (1.0 + (-2.0f32).exp()).ln()).abs() < 1e-6);
    // Candle graph: mean over [0, 50, -50, 2] with labels [1, 0, 1, 1].
    let x = Var::from_slice(&[0.0f32, 50.0, -50.0, 2.0], 4, &Device::Cpu).unwrap();
    let y = t1(&[1.0, 0.0, 1.0, 1.0]);
    let l = bce_with_logits(x.as_tensor(), &y).unwrap();
    let want = (ln2 + 50.0 + 50.0 + (1.0 + (-2.0f32).exp()).ln()) / 4.0;
    let got = l.to_scalar::<f32>().unwrap();
    assert!((got - want).abs() < 1e-4, "{got} vs {want}");
    // Gradient (sigmoid(x) - y) / n is finite at |x| = 50.
    let g = l.backward().unwrap().get(x.as_tensor()).unwrap().to_vec1::<f32>().unwrap();
    let want_g = [(0.5 - 1.0) / 4.0, 1.0 / 4.0, -1.0 / 4.0, (1.0 / (1.0 + (-2.0f32).exp()) - 1.0) / 4.0];
    for (a, b) in g.iter().zip(want_g) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

#[test]
fn hinge_hand_computed() {
    let cfg = LossConfig::default();
    // z+ = (0,0), z- = (0.3, 0.4): distance 0.5, hinge (1 - 0.5)^2 = 0.25, two pairs.
    let z = Tensor::from_slice(&[0.0f32, 0.0, 0.3, 0.4], (2, 2), &Device::Cpu).unwrap();
    let h = contrastive_hinge(&z, &[1.0, 0.0], &cfg).unwrap().unwrap().to_scalar::<f32>().unwrap();
    assert!((h - 0.25).abs() < 1e-6, "{h}");
    // Distance 1.0 = margin: zero.
    let z = Tensor::from_slice(&[0.0f32, 0.0, 0.6, 0.8], (2, 2), &Device::Cpu).unwrap();
    let h = contrastive_hinge(&z, &[1.0, 0.0], &cfg).unwrap().unwrap().to_scalar::<f32>().unwrap();
    assert!(h.abs() < 1e-6);
    // One class only: no pairs.
    assert!(contrastive_hinge(&z, &[1.0, 1.0], &cfg).unwrap().is_none());
    // Pairing: positives [0, 2], negatives [1]: (0,1), (2,1), (1,0).
    let (a, b) = contrastive_pairs(&[1.0, 0.0, 1.0]);
    assert_eq!(a, vec![0, 2, 1]);
    assert_eq!(b, vec![1, 1, 0]);
    // Identical embeddings: finite gradient thanks to eps.
    let zv = Var::from_slice(&[0.5f32, 0.5, 0.5, 0.5], (2, 2), &Device::Cpu).unwrap();
    let h = contrastive_hinge(zv.as_tensor(), &[1.0, 0.0], &cfg).unwrap().unwrap();
    assert!((h.to_scalar::<f32>().unwrap() - 1.0).abs() < 1e-3);
    let g =
        h.backward().unwrap().get(zv.as_tensor()).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert!(g.iter().all(|v| v.is_finite()));
}

#[test]
fn mse_hand_computed() {
    let l = mse(&t1(&[1.0, 2.0, 0.5]), &t1(&[0.0, 0.0, 0.5])).unwrap().to_scalar::<f32>().unwrap();
    assert!((l - 5.0 / 3.0).abs() < 1e-6);
    let v = objective_host(Kind::Q, &[1.0, 2.0, 0.5], &[], 0, &[0.0, 0.0, 0.5], &LossConfig::default(), None);
    assert!((v - 5.0 / 3.0).abs() < 1e-6);
}

#[test]
fn host_objective_matches_candle_value_and_gradients() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (b, zd) = (17, 6);
    let yv: Vec<f32> = (0..b).map(|_| rng.gen_range(-3.0..3.0)).collect();
    let zv: Vec<f32> = (0..b * zd).map(|_| rng.gen_range(-0.4..0.4)).collect();
    let cfg = LossConfig::default();
    for kind in [Kind::Classifier, Kind::Q] {
        let target: Vec<f32> = match kind {
            Kind::Classifier => (0..b).map(|i| (i % 3 == 0) as u8 as f32).collect(),
            Kind::Q => (0..b).map(|i| 0.9f32.powi(i as i32)).collect(),
        };
        let y = Var::from_slice(&yv, b, &Device::Cpu).unwrap();
        let z = Var::from_slice(&zv, (b, zd), &Device::Cpu).unwrap();
        let l = objective(kind, y.as_tensor(), z.as_tensor(), &target, &cfg).unwrap();
        let g = l.backward().unwrap();
        let (mut dy, mut dz) = (vec![0f32; b], vec![0f32; b * zd]);
        let hv = objective_host(kind, &yv, &zv, zd, &target, &cfg, Some((&mut dy, &mut dz)));
        let cv = l.to_scalar::<f32>().unwrap() as f64;
        assert!((hv - cv).abs() < 1e-5, "{kind:?}: host {hv} vs candle {cv}");
        let gy = g.get(y.as_tensor()).unwrap().to_vec1::<f32>().unwrap();
        for (a, c) in dy.iter().zip(&gy) {
            assert!((a - c).abs() < 1e-6);
        }
        if kind == Kind::Classifier {
            assert!(dz.iter().any(|v| v.abs() > 1e-4), "hinge gradient should be active");
            let gz = g.get(z.as_tensor()).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            for (a, c) in dz.iter().zip(&gz) {
                assert!((a - c).abs() < 1e-6, "dz {a} vs {c}");
            }
        }
    }
}

#[test]
fn grad_clipping_to_global_norm() {
    let mut g = vec![vec![3.0f32], vec![0.0, 4.0]];
    let n = clip_grad_norm(&mut g, 1.0);
    assert!((n - 5.0).abs() < 1e-9);
    assert!((g[0][0] - 0.6).abs() < 1e-6 && (g[1][1] - 0.8).abs() < 1e-6);
    assert!((global_norm(&g) - 1.0).abs() < 1e-5);
    let mut small = vec![vec![0.3f32, 0.4]];
    clip_grad_norm(&mut small, 1.0);
    assert_eq!(small, vec![vec![0.3f32, 0.4]]);
}

#[test]
fn adamw_matches_candle_nn() {
    use candle_nn::Optimizer;
    let cfg = AdamWConfig::default();
    let p0 = vec![0.5f32, -1.0, 2.0];
    let var = Var::from_slice(&p0, 3, &Device::Cpu).unwrap();
    let mut copt = candle_nn::AdamW::new(
        vec![var.clone()],
        candle_nn::ParamsAdamW {
            lr: cfg.lr,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            eps: cfg.eps,
            weight_decay: cfg.weight_decay,
        },
    )
    .unwrap();
    let mut mine = AdamW::new(cfg, [3]);
    let mut p = vec![p0.clone()];
    for step in 0..5 {
        let gv = vec![0.1f32 * (step as f32 + 1.0), -0.3, 0.02];
        // loss = sum(p * g) has gradient g.
        let loss = var.as_tensor().mul(&t1(&gv)).unwrap().sum_all().unwrap();
        copt.backward_step(&loss).unwrap();
        mine.step(&mut p, &[gv], cfg.lr);
    }
    let c = var.as_tensor().to_vec1::<f32>().unwrap();
    for (a, b) in p[0].iter().zip(&c) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
    assert!((linear_factor(0, 100, 1.0, 0.01) - 1.0).abs() < 1e-12);
    assert!((linear_factor(50, 100, 1.0, 0.01) - 0.505).abs() < 1e-12);
    assert!((linear_factor(100, 100, 1.0, 0.01) - 0.01).abs() < 1e-12);
}

fn brute_auc(s: &[f32], l: &[f32]) -> f64 {
    let (mut num, mut den) = (0f64, 0f64);
    for i in 0..s.len() {
        for j in 0..s.len() {
            if l[i] > 0.5 && l[j] <= 0.5 {
                den += 1.0;
                num += if s[i] > s[j] {
                    1.0
                } else if s[i] == s[j] {
                    0.5
                } else {
                    0.0
                };
            }
        }
    }
    num / den
}

#[test]
fn auc_matches_brute_force_with_ties() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for _ in 0..20 {
        let n = rng.gen_range(5..60);
        // Few distinct values => many ties.
        let s: Vec<f32> = (0..n).map(|_| rng.gen_range(0..6) as f32 * 0.5).collect();
        let mut l: Vec<f32> = (0..n).map(|_| rng.gen_range(0..2) as f32).collect();
        l[0] = 1.0;
        l[1] = 0.0;
        let a = roc_auc(&s, &l).unwrap();
        assert!((a - brute_auc(&s, &l)).abs() < 1e-12);
    }
    assert_eq!(roc_auc(&[0.1, 0.9, 0.5], &[0.0, 1.0, 0.0]), Some(1.0));
    assert_eq!(roc_auc(&[0.1, 0.9], &[1.0, 1.0]), None);
    assert!((pearson(&[1.0, 2.0, 3.0], &[2.0, 4.0, 6.0]).unwrap() - 1.0).abs() < 1e-12);
    assert!((pearson(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]).unwrap() + 1.0).abs() < 1e-12);
}
