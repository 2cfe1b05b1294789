use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use steer::fast::FastLowdim;
use steer::reference::CandleVerifier;
use steer::testutil::{write_artifact, RandomSpec};
use steer::weights::{temb, Weights};
use steer::{Scorer, SteerError, Verifier};

fn randv(rng: &mut ChaCha8Rng, n: usize, s: f32) -> Vec<f32> {
    use rand::Rng;
    (0..n).map(|_| rng.gen_range(-s..s)).collect()
}

fn close(a: &[f32], b: &[f32], tol: f32, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol * y.abs().max(1.0), "{what}[{i}]: {x} vs {y}");
    }
}

fn specs() -> Vec<RandomSpec> {
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
    let deep_q = RandomSpec { kind: "q", trunk_dims: vec![40, 24, 9], ..RandomSpec::nav() };
    vec![RandomSpec::square(), RandomSpec::nav(), odd, deep_q]
}

#[test]
fn fast_matches_candle_values_and_gradients() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for spec in specs() {
        let (cfg, w) = spec.build(&mut rng);
        let reference = CandleVerifier::new(&cfg, &w).unwrap();
        for simd in [true, false] {
            let fast = FastLowdim::with_simd(&cfg, &w, simd).unwrap();
            let (od, ad) = (cfg.obs_dim(), cfg.act_dim());
            for &(b, n) in &[(1usize, 10usize), (3, 5), (2, 1)] {
                let obs = randv(&mut rng, b * od, 2.0);
                let t: Vec<u32> = (0..b as u32).map(|i| 7 + 13 * i).collect();
                let cands = randv(&mut rng, b * n * ad, 2.0);
                let sr = reference.score_batch(&obs, &t, &cands, n).unwrap();
                let sf = fast.score_batch(&obs, &t, &cands, n).unwrap();
                close(&sf, &sr, 1e-5, &format!("score {:?} simd={simd}", spec.trunk_dims));
                let chunks = &cands[..b * ad];
                let gr = reference.grad_batch(&obs, &t, chunks).unwrap();
                let gf = fast.grad_batch(&obs, &t, chunks).unwrap();
                assert!(gr.iter().any(|g| g.abs() > 1e-4), "gradient is trivially zero");
                close(&gf, &gr, 1e-5, &format!("grad {:?} simd={simd}", spec.trunk_dims));
            }
        }
    }
}

#[test]
fn reference_gradient_matches_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for spec in [
        RandomSpec::nav(),
        RandomSpec { kind: "q", ..RandomSpec::nav() },
        RandomSpec {
            variant: "features",
            input_layernorm: true,
            encoder_layernorm: true,
            extra_inputs: vec![("lang".into(), 5, 4)],
            ..RandomSpec::nav()
        },
    ] {
        let (cfg, w) = spec.build(&mut rng);
        let v = CandleVerifier::new(&cfg, &w).unwrap();
        let obs = randv(&mut rng, cfg.obs_dim(), 1.0);
        let chunk = randv(&mut rng, cfg.act_dim(), 1.0);
        let extra = randv(&mut rng, 5, 1.0);
        let extras: Vec<&[f32]> = if spec.extra_inputs.is_empty() { vec![] } else { vec![&extra] };
        let f = |c: &[f32]| -> f64 {
            let s = v.score_batch_ext(&obs, &extras, &[3], c, 1).unwrap()[0] as f64;
            if spec.kind == "q" { s } else { s.ln() }
        };
        let g = v.grad_batch_ext(&obs, &extras, &[3], &chunk).unwrap();
        for j in 0..cfg.act_dim() {
            let h = 1e-2f32;
            let mut p = chunk.clone();
            p[j] += h;
            let mut m = chunk.clone();
            m[j] -= h;
            let fd = (f(&p) - f(&m)) / (2.0 * h as f64);
            assert!((fd - g[j] as f64).abs() < 2e-3 + 2e-2 * fd.abs(), "{} d/da[{j}]: fd {fd} vs {}", spec.variant, g[j]);
        }
    }
}

#[test]
fn temb_follows_the_contract() {
    let mut e = [0f32; 4];
    temb(1, 4, &mut e);
    let want = [1f64.sin(), 1f64.cos(), 0.01f64.sin(), 0.01f64.cos()];
    for j in 0..4 {
        assert!((e[j] as f64 - want[j]).abs() < 1e-7, "{j}");
    }
}

#[test]
fn load_dir_roundtrip_and_fast_path_pick() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let dir = tempfile::tempdir().unwrap();
    let (cfg, w) = RandomSpec::nav().build(&mut rng);
    let id = write_artifact(dir.path(), &cfg, &w).unwrap();
    let v = Verifier::load_dir(dir.path()).unwrap();
    assert_eq!(v.id(), Some(id.as_str()));
    assert!(v.is_fast());
    let r = Verifier::from_parts_reference(cfg.clone(), &w).unwrap();
    let obs = randv(&mut rng, 4, 1.0);
    let c = randv(&mut rng, 16 * 3, 1.0);
    close(&v.score(&obs, &c, 5).unwrap(), &r.score(&obs, &c, 5).unwrap(), 1e-5, "score");
    // features variant goes to candle
    let (cfg, w) = RandomSpec { variant: "features", ..RandomSpec::nav() }.build(&mut rng);
    let v = Verifier::from_parts(cfg, &w).unwrap();
    assert_eq!(v.backend_name(), "candle");
    assert_eq!(v.score(&obs, &c, 5).unwrap().len(), 3);
    // wrong input lengths are errors, not panics
    assert!(matches!(v.score(&obs[..3], &c, 5), Err(SteerError::Input(_))));
    assert!(matches!(v.score(&obs, &c[..15], 5), Err(SteerError::Input(_))));
}

fn rewrite(dir: &std::path::Path, file: &str, bytes: &[u8], fix_manifest: bool) {
    std::fs::write(dir.join(file), bytes).unwrap();
    if fix_manifest {
        let m = std::fs::read(dir.join("manifest.json")).unwrap();
        let mut m: serde_json::Value = serde_json::from_slice(&m).unwrap();
        m["files"][file] = steer::verifier::sha256_hex(bytes).into();
        std::fs::write(dir.join("manifest.json"), serde_json::to_vec(&m).unwrap()).unwrap();
    }
}

#[test]
fn bad_artifacts_are_clear_errors() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (cfg, w) = RandomSpec::nav().build(&mut rng);
    let fresh = || {
        let d = tempfile::tempdir().unwrap();
        write_artifact(d.path(), &cfg, &w).unwrap();
        d
    };
    let cfg_json = || -> serde_json::Value { serde_json::to_value(&cfg).unwrap() };

    // tampered file -> hash mismatch
    let d = fresh();
    let mut c = cfg_json();
    c["gamma"] = 0.5.into();
    rewrite(d.path(), "config.json", &serde_json::to_vec(&c).unwrap(), false);
    assert!(matches!(Verifier::load_dir(d.path()), Err(SteerError::HashMismatch { .. })));

    // missing file
    let d = fresh();
    std::fs::remove_file(d.path().join("model.safetensors")).unwrap();
    assert!(matches!(Verifier::load_dir(d.path()), Err(SteerError::Io { .. })));

    // unknown schema / variant / kind / activation
    for (field, val, check) in [
        ("schema_version", serde_json::json!(2), "schema"),
        ("variant", serde_json::json!("conv"), "variant"),
        ("kind", serde_json::json!("reward"), "kind"),
        ("activation", serde_json::json!("tanh"), "activation"),
    ] {
        let d = fresh();
        let mut c = cfg_json();
        match field {
            "variant" | "activation" => c["architecture"][field] = val,
            _ => c[field] = val,
        }
        rewrite(d.path(), "config.json", &serde_json::to_vec(&c).unwrap(), true);
        let e = Verifier::load_dir(d.path()).err().expect("must fail");
        let ok = match check {
            "schema" => matches!(e, SteerError::UnknownSchema(2)),
            "variant" => matches!(e, SteerError::UnknownVariant(_)),
            "kind" => matches!(e, SteerError::UnknownKind(_)),
            _ => matches!(e, SteerError::UnknownActivation(_)),
        };
        assert!(ok, "{field}: got {e}");
    }
    // manifest schema
    let d = fresh();
    std::fs::write(d.path().join("manifest.json"), br#"{"schema_version": 3, "files": {}}"#).unwrap();
    assert!(matches!(Verifier::load_dir(d.path()), Err(SteerError::UnknownSchema(3))));

    // truncated safetensors (with a matching hash): parse error, no panic
    let st = w.to_safetensors();
    for cut in [0, 5, 40, st.len() / 2, st.len() - 1] {
        let d = fresh();
        rewrite(d.path(), "model.safetensors", &st[..cut], true);
        assert!(matches!(Verifier::load_dir(d.path()), Err(SteerError::Safetensors(_))), "cut {cut}");
    }
    // missing tensor, wrong shape
    let mut w2 = Weights { tensors: w.tensors.clone() };
    w2.tensors.remove("trunk.1.ln.bias");
    let e = Verifier::from_bytes(&serde_json::to_vec(&cfg).unwrap(), &w2.to_safetensors()).err().unwrap();
    assert!(matches!(&e, SteerError::MissingTensor { name } if name == "trunk.1.ln.bias"), "{e}");
    let mut w3 = Weights { tensors: w.tensors.clone() };
    w3.insert("act_enc.0.weight", vec![64, 15], vec![0.0; 64 * 15]);
    let e = Verifier::from_bytes(&serde_json::to_vec(&cfg).unwrap(), &w3.to_safetensors()).err().unwrap();
    assert!(matches!(&e, SteerError::TensorShape { name, .. } if name == "act_enc.0.weight"), "{e}");
    // inconsistent config dims
    let mut c = cfg_json();
    c["input"]["act_dim"] = 15.into();
    assert!(matches!(Verifier::from_bytes(&serde_json::to_vec(&c).unwrap(), &st), Err(SteerError::Config(_))));
    assert!(matches!(Verifier::from_bytes(b"{", &st), Err(SteerError::Config(_))));
}
