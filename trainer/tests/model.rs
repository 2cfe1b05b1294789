//! Model tests: gradients reach every parameter, the explicit LayerNorm, spectral norm, and the
//! fused fast path against the candle graph (values and gradients).

use crate::common;

use candle_core::{Device, Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use trainer::data::TimeEmbedTable;
use trainer::fast::{BatchSource, FastModel};
use trainer::loss::{objective, LossConfig};
use trainer::model::{
    layer_norm, power_iterate, sigma_uv, spectral_norm_estimate, Architecture, CandleModel, ExtraInput, Kind,
    ModelSpec, TrainNoise,
};

fn rand_vec(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| common::normal(rng)).collect()
}

fn batch(model: &CandleModel, b: usize, rng: &mut ChaCha8Rng) -> (trainer::model::BatchTensors, Vec<f32>) {
    let s = &model.spec;
    let obs = rand_vec(rng, b * s.obs_dim);
    let act = rand_vec(rng, b * s.act_dim);
    let mut temb = vec![0f32; b * s.arch.t_embed_dim];
    for i in 0..b {
        trainer::data::time_embedding_into(
            i as f64 * 3.0,
            &mut temb[i * s.arch.t_embed_dim..(i + 1) * s.arch.t_embed_dim],
        );
    }
    let extras: Vec<Vec<f32>> = s.arch.extra_inputs.iter().map(|e| rand_vec(rng, b * e.dim)).collect();
    let ex: Vec<&[f32]> = extras.iter().map(|v| v.as_slice()).collect();
    let labels: Vec<f32> = (0..b).map(|i| (i % 3 == 0) as u8 as f32).collect();
    (model.batch_tensors(b, &obs, &act, &temb, &ex).unwrap(), labels)
}

fn check_all_grads(spec: &ModelSpec, with_noise: bool) {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let params = spec.init_params(&mut rng);
    let model = CandleModel::new(spec, &params, &mut rng).unwrap();
    model.power_iteration(1).unwrap();
    let b = 12;
    let (bt, labels) = batch(&model, b, &mut rng);
    let zdim = *spec.arch.trunk_dims.last().unwrap();
    let mask: Vec<f32> = (0..b * zdim).map(|i| if i % 2 == 0 { 2.0 } else { 0.0 }).collect();
    let noise = TrainNoise {
        drop_mask: Some(Tensor::from_slice(&mask, (b, zdim), &Device::Cpu).unwrap()),
        obs_noise: with_noise.then(|| {
            Tensor::from_vec(rand_vec(&mut rng, b * spec.obs_dim), (b, spec.obs_dim), &Device::Cpu)
                .unwrap()
                .affine(0.02, 0.0)
                .unwrap()
        }),
    };
    let (y, z) = model.forward(&bt, &noise).unwrap();
    let target: Vec<f32> = match spec.kind {
        Kind::Classifier => labels,
        Kind::Q => (0..b).map(|i| 0.9f32.powi(i as i32)).collect(),
    };
    let loss = objective(spec.kind, &y, &z, &target, &LossConfig::default()).unwrap();
    let grads = loss.backward().unwrap();
    assert_eq!(model.vars().len(), params.len());
    for (name, var) in model.names().iter().zip(model.vars()) {
        let g = grads.get(var.as_tensor()).unwrap_or_else(|| panic!("no gradient for {name}"));
        let norm: f32 = g.sqr().unwrap().sum_all().unwrap().to_scalar().unwrap();
        assert!(norm > 0.0 && norm.is_finite(), "zero/NaN gradient for {name}: {norm}");
    }
}

#[test]
fn gradients_reach_every_parameter_lowdim() {
    for kind in [Kind::Classifier, Kind::Q] {
        let spec = ModelSpec { kind, arch: Architecture::lowdim(), obs_dim: 7, act_dim: 10 };
        check_all_grads(&spec, false);
    }
}

#[test]
fn gradients_reach_every_parameter_features_with_extras() {
    let mut arch = Architecture::features();
    arch.encoder_width = 16;
    arch.t_embed_dim = 8;
    arch.trunk_dims = vec![24, 12];
    arch.extra_inputs = vec![
        ExtraInput { name: "lang".into(), dim: 5, width: 4 },
        ExtraInput { name: "proprio".into(), dim: 3, width: 6 },
    ];
    for kind in [Kind::Classifier, Kind::Q] {
        let spec = ModelSpec { kind, arch: arch.clone(), obs_dim: 9, act_dim: 6 };
        check_all_grads(&spec, true);
    }
}

#[test]
fn layer_norm_values_and_gradients() {
    let dev = Device::Cpu;
    let x = Var::from_vec(vec![1.0f32, 2.0, 4.0, -1.0, 0.5, 0.5, 3.0, -2.0], (2, 4), &dev).unwrap();
    let w = Var::from_vec(vec![1.0f32, 2.0, 0.5, -1.0], 4, &dev).unwrap();
    let b = Var::from_vec(vec![0.1f32, 0.0, -0.2, 0.3], 4, &dev).unwrap();
    let eps = 1e-5;
    let y = layer_norm(x.as_tensor(), w.as_tensor(), b.as_tensor(), eps).unwrap();
    // Reference values.
    let xv = x.as_tensor().to_vec2::<f32>().unwrap();
    let yv = y.to_vec2::<f32>().unwrap();
    let wv = [1.0f32, 2.0, 0.5, -1.0];
    let bv = [0.1f32, 0.0, -0.2, 0.3];
    for r in 0..2 {
        let m: f32 = xv[r].iter().sum::<f32>() / 4.0;
        let var: f32 = xv[r].iter().map(|v| (v - m) * (v - m)).sum::<f32>() / 4.0;
        for k in 0..4 {
            let want = (xv[r][k] - m) / (var + eps as f32).sqrt() * wv[k] + bv[k];
            assert!((yv[r][k] - want).abs() < 1e-5);
        }
    }
    // Gradient of sum(y * c) vs finite differences (f64 by re-evaluation).
    let c = Tensor::from_vec(vec![0.3f32, -1.0, 2.0, 0.7, 1.1, 0.2, -0.4, 0.9], (2, 4), &dev).unwrap();
    let loss = y.mul(&c).unwrap().sum_all().unwrap();
    let g = loss.backward().unwrap();
    for var in [&x, &w, &b] {
        let gv = g
            .get(var.as_tensor())
            .expect("LayerNorm gradient missing")
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(gv.iter().any(|v| v.abs() > 1e-4));
        let base = var.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let shape = var.as_tensor().dims().to_vec();
        for i in 0..base.len() {
            let eval = |d: f32| {
                let mut v = base.clone();
                v[i] += d;
                let t = Tensor::from_vec(v, shape.as_slice(), &dev).unwrap();
                let (xx, ww, bb) = if std::ptr::eq(var, &x) {
                    (t, w.as_tensor().clone(), b.as_tensor().clone())
                } else if std::ptr::eq(var, &w) {
                    (x.as_tensor().clone(), t, b.as_tensor().clone())
                } else {
                    (x.as_tensor().clone(), w.as_tensor().clone(), t)
                };
                layer_norm(&xx, &ww, &bb, eps)
                    .unwrap()
                    .mul(&c)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            };
            let fd = (eval(1e-2) - eval(-1e-2)) / 2e-2;
            assert!((fd - gv[i]).abs() < 2e-2, "grad {i}: fd {fd} vs autograd {}", gv[i]);
        }
    }
}

#[test]
fn spectral_norm_power_iteration() {
    // W = R1 diag(3, 2, 0.5) R2 (rotations), largest singular value 3.
    let (a, b) = (0.3f64, 1.1f64);
    let r1 = [[a.cos(), -a.sin(), 0.0], [a.sin(), a.cos(), 0.0], [0.0, 0.0, 1.0]];
    let r2 = [[1.0, 0.0, 0.0], [0.0, b.cos(), -b.sin()], [0.0, b.sin(), b.cos()]];
    let s = [3.0, 2.0, 0.5];
    let mut w = vec![0f32; 9];
    for i in 0..3 {
        for j in 0..3 {
            w[i * 3 + j] = (0..3).map(|k| r1[i][k] * s[k] * r2[k][j]).sum::<f64>() as f32;
        }
    }
    let sigma = spectral_norm_estimate(&w, 3, 3, 50, 7);
    assert!((sigma - 3.0).abs() < 1e-4, "sigma {sigma}");
    let wn: Vec<f32> = w.iter().map(|v| v / sigma).collect();
    let s2 = spectral_norm_estimate(&wn, 3, 3, 50, 9);
    assert!((s2 - 1.0).abs() < 1e-4, "normalised sigma {s2}");
    // sigma_uv with exact vectors.
    let mut u = vec![1.0f32, 0.0, 0.0];
    let mut v = vec![0.0f32, 1.0, 0.0];
    power_iterate(&w, 3, 3, &mut u, &mut v, 100);
    assert!((sigma_uv(&w, &u, &v) - 3.0).abs() < 1e-4);

    // In the model: after enough power iterations the exported (folded) weights have sigma ~ 1.
    let mut arch = Architecture::features();
    arch.encoder_width = 8;
    arch.t_embed_dim = 4;
    arch.trunk_dims = vec![8, 6];
    let spec = ModelSpec { kind: Kind::Q, arch, obs_dim: 5, act_dim: 4 };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let p = spec.init_params(&mut rng);
    let m = CandleModel::new(&spec, &p, &mut rng).unwrap();
    m.power_iteration(200).unwrap();
    let raw = p.get("trunk.0.weight").unwrap();
    let want = spectral_norm_estimate(raw, 8, 20, 500, 1);
    assert!((m.sigma("trunk.0").unwrap() - want).abs() < 1e-3 * want);
    let inf = m.inference_params().unwrap();
    for layer in ["obs_enc.0", "obs_enc.1", "act_enc.0", "act_enc.1", "trunk.0", "trunk.1"] {
        let i = inf.index(&format!("{layer}.weight")).unwrap();
        let sh = &inf.shapes[i];
        let s = spectral_norm_estimate(&inf.values[i], sh[0], sh[1], 500, 2);
        assert!((s - 1.0).abs() < 1e-3, "{layer}: sigma after normalisation {s}");
    }
    // The head is not normalised.
    assert_eq!(inf.get("head.weight"), p.get("head.weight"));
}

fn fast_vs_candle(kind: Kind, threads: usize, portable: bool) {
    let spec = ModelSpec { kind, arch: Architecture::lowdim(), obs_dim: 46, act_dim: 40 };
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let params = spec.init_params(&mut rng);
    let model = CandleModel::new(&spec, &params, &mut rng).unwrap();
    let b = 37;
    let n = 60;
    let obs = rand_vec(&mut rng, n * spec.obs_dim);
    let act = rand_vec(&mut rng, n * spec.act_dim);
    let t: Vec<u32> = (0..n as u32).map(|i| i * 7 % 90).collect();
    let mut table = TimeEmbedTable::new(64);
    table.ensure(100);
    let rows: Vec<u32> = (0..b as u32).map(|i| (i * 13 + 5) % n as u32).collect();
    let target: Vec<f32> = match kind {
        Kind::Classifier => rows.iter().map(|&r| (r % 3 != 0) as u8 as f32).collect(),
        Kind::Q => rows.iter().map(|&r| 0.97f32.powi(r as i32)).collect(),
    };
    let zdim = 64;
    let mask: Vec<f32> = (0..b * zdim).map(|i| if (i * 7919) % 5 < 2 { 0.0 } else { 2.0 }).collect();
    let cfg = LossConfig { contrastive_margin: 4.0, ..Default::default() }; // make the hinge active
                                                                            // Candle reference.
    let s = trainer::Samples {
        obs_dim: 46,
        act_dim: 40,
        obs: obs.clone(),
        act: act.clone(),
        t: t.clone(),
        ..Default::default()
    };
    let bt = trainer::train::gather_tensors(&model, &s, &table, &rows).unwrap();
    // Observation noise (obs_noise_std > 0): the fast path must honour it like the candle graph.
    let obs_noise: Vec<f32> = rand_vec(&mut rng, b * spec.obs_dim).iter().map(|v| 0.05 * v).collect();
    let noise = TrainNoise {
        drop_mask: Some(Tensor::from_slice(&mask, (b, zdim), &Device::Cpu).unwrap()),
        obs_noise: Some(Tensor::from_slice(&obs_noise, (b, spec.obs_dim), &Device::Cpu).unwrap()),
    };
    let (y, z) = model.forward(&bt, &noise).unwrap();
    let loss = objective(kind, &y, &z, &target, &cfg).unwrap();
    let grads = loss.backward().unwrap();
    // Fast path.
    let mut f = FastModel::new(&spec, &params, 64, threads).unwrap();
    if portable {
        f.force_portable();
    }
    let src = BatchSource { obs: &obs, act: &act, t: &t, temb: &table };
    let fl = f.loss_and_grads(&params, &src, &rows, &target, Some(&mask), Some(&obs_noise), kind, &cfg);
    let cl = loss.to_scalar::<f32>().unwrap() as f64;
    assert!((fl - cl).abs() < 1e-5 * (1.0 + cl.abs()), "loss fast {fl} vs candle {cl}");
    let yv = y.to_vec1::<f32>().unwrap();
    let zv = z.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for (a, b) in f.y()[..b].iter().zip(&yv) {
        assert!((a - b).abs() < 1e-5 * (1.0 + b.abs()), "y {a} vs {b}");
    }
    for (a, b) in f.z()[..b * zdim].iter().zip(&zv) {
        assert!((a - b).abs() < 1e-5 * (1.0 + b.abs()), "z {a} vs {b}");
    }
    for (i, (name, var)) in model.names().iter().zip(model.vars()).enumerate() {
        let g = grads.get(var.as_tensor()).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let scale = g.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-3);
        for (k, (a, c)) in f.grads[i].iter().zip(&g).enumerate() {
            assert!(
                (a - c).abs() < 1e-5 * scale * 10.0 + 1e-6,
                "{name}[{k}]: fast {a} vs candle {c} (scale {scale})"
            );
        }
    }
    // Eval-mode forward without mask.
    f.forward(&params, &src, &rows, None, None);
    let (y2, _) = model.forward(&bt, &TrainNoise::default()).unwrap();
    for (a, b) in f.y()[..b].iter().zip(&y2.to_vec1::<f32>().unwrap()) {
        assert!((a - b).abs() < 1e-5 * (1.0 + b.abs()));
    }
}

#[test]
fn fast_path_matches_candle_classifier() {
    fast_vs_candle(Kind::Classifier, 1, false);
}

#[test]
fn fast_path_matches_candle_q() {
    fast_vs_candle(Kind::Q, 1, false);
}

#[test]
fn fast_path_matches_candle_two_threads_and_portable_kernels() {
    fast_vs_candle(Kind::Classifier, 2, false);
    fast_vs_candle(Kind::Classifier, 1, true);
}
