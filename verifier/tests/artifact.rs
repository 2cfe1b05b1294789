//! Loading: every file checked against the manifest, clear errors for every kind of bad
//! artifact, the id, and the files as the trainer writes them.

use std::path::Path;

use verifier::testutil::RandomSpec;
use verifier::{
    sha256_hex, ActionSpace, Artifact, ArtifactConfig, ArtifactFiles, Verifier, VerifierError, Weights,
};

fn write(dir: &Path, cfg: &ArtifactConfig, w: &Weights) -> String {
    let f = ArtifactFiles::build(cfg, w).unwrap();
    f.write_dir(dir).unwrap();
    f.id
}

/// Replace `file` in `dir`; with `fix_manifest` the manifest's hash is updated too (so the
/// content itself is what is tested, not the hash check).
fn rewrite(dir: &Path, file: &str, bytes: &[u8], fix_manifest: bool) {
    std::fs::write(dir.join(file), bytes).unwrap();
    if fix_manifest {
        let m = std::fs::read(dir.join("manifest.json")).unwrap();
        let mut m: serde_json::Value = serde_json::from_slice(&m).unwrap();
        m["files"][file] = sha256_hex(bytes).into();
        std::fs::write(dir.join("manifest.json"), serde_json::to_vec(&m).unwrap()).unwrap();
    }
}

#[test]
fn load_dir_roundtrip_and_id() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, w) = RandomSpec::nav().build(3);
    let id = write(dir.path(), &cfg, &w);
    let manifest = std::fs::read(dir.path().join("manifest.json")).unwrap();
    assert_eq!(id, sha256_hex(&manifest)[..16]);
    let a = Artifact::load_dir(dir.path()).unwrap();
    assert_eq!(a.id.as_deref(), Some(id.as_str()));
    assert_eq!(a.config, cfg);
    assert_eq!(a.weights, w);
    let v = Verifier::load_dir(dir.path()).unwrap();
    assert_eq!(v.id(), Some(id.as_str()));
    // The same weights and config give the same bytes, hence the same id.
    assert_eq!(ArtifactFiles::build(&cfg, &w).unwrap().id, id);
    // Through a getter (the store / HTTP path) with the same checks and the same id.
    let got =
        Verifier::load_with(&manifest, |name| Ok(std::fs::read(dir.path().join(name)).unwrap())).unwrap();
    assert_eq!(got.id(), Some(id.as_str()));
    let obs = vec![0.1; v.obs_dim()];
    let c = vec![0.2; 3 * v.act_dim()];
    assert_eq!(v.score(&obs, &[5], &c, 3).unwrap(), got.score(&obs, &[5], &c, 3).unwrap());
    // A getter's failure is reported as what it was fetching.
    let e = Verifier::load_with(&manifest, |name| {
        Err(VerifierError::Fetch { file: name.into(), message: "connection reset".into() })
    })
    .err()
    .unwrap();
    assert!(e.to_string().contains("connection reset"), "{e}");
}

#[test]
fn bad_artifacts_are_clear_errors() {
    let (cfg, w) = RandomSpec::nav().build(4);
    let fresh = || {
        let d = tempfile::tempdir().unwrap();
        write(d.path(), &cfg, &w);
        d
    };
    let cfg_json = || -> serde_json::Value { serde_json::to_value(&cfg).unwrap() };

    // Tampered file: hash mismatch, nothing parsed.
    let d = fresh();
    let mut c = cfg_json();
    c["gamma"] = 0.5.into();
    rewrite(d.path(), "config.json", &serde_json::to_vec(&c).unwrap(), false);
    assert!(matches!(Verifier::load_dir(d.path()), Err(VerifierError::HashMismatch { .. })));

    // Missing file.
    let d = fresh();
    std::fs::remove_file(d.path().join("model.safetensors")).unwrap();
    assert!(matches!(Verifier::load_dir(d.path()), Err(VerifierError::Io { .. })));

    // Unknown schema / variant / kind / activation, each its own error.
    for (field, val) in [
        ("schema_version", serde_json::json!(3)),
        ("variant", serde_json::json!("conv")),
        ("kind", serde_json::json!("reward")),
        ("activation", serde_json::json!("tanh")),
    ] {
        let d = fresh();
        let mut c = cfg_json();
        match field {
            "variant" | "activation" => c["architecture"][field] = val,
            _ => c[field] = val,
        }
        rewrite(d.path(), "config.json", &serde_json::to_vec(&c).unwrap(), true);
        let e = Verifier::load_dir(d.path()).expect_err("must fail");
        let ok = match field {
            "schema_version" => matches!(e, VerifierError::UnknownSchema(3)),
            "variant" => matches!(e, VerifierError::UnknownVariant(_)),
            "kind" => matches!(e, VerifierError::UnknownKind(_)),
            _ => matches!(e, VerifierError::UnknownActivation(_)),
        };
        assert!(ok, "{field}: got {e}");
    }
    // An architecture flag this client does not know: refused, it could change the forward pass.
    let d = fresh();
    let mut c = cfg_json();
    c["architecture"]["residual"] = true.into();
    rewrite(d.path(), "config.json", &serde_json::to_vec(&c).unwrap(), true);
    let e = Verifier::load_dir(d.path()).err().unwrap().to_string();
    assert!(e.contains("residual"), "{e}");

    // Manifest: unknown schema, a file name that leaves the directory.
    let d = fresh();
    std::fs::write(d.path().join("manifest.json"), br#"{"schema_version": 3, "files": {}}"#).unwrap();
    assert!(matches!(Verifier::load_dir(d.path()), Err(VerifierError::UnknownSchema(3))));
    let d = fresh();
    let m = std::fs::read_to_string(d.path().join("manifest.json")).unwrap();
    let m = m.replacen("\"files\": {", "\"files\": {\"../../etc/passwd\": \"00\",", 1);
    std::fs::write(d.path().join("manifest.json"), m).unwrap();
    assert!(matches!(Verifier::load_dir(d.path()), Err(VerifierError::Manifest(_))));

    // Truncated safetensors (with a matching hash): a parse error, no panic.
    let st = w.to_safetensors().unwrap();
    for cut in [0, 5, 40, st.len() / 2, st.len() - 1] {
        let d = fresh();
        rewrite(d.path(), "model.safetensors", &st[..cut], true);
        assert!(matches!(Verifier::load_dir(d.path()), Err(VerifierError::Safetensors(_))), "cut {cut}");
    }
    // Missing tensor, wrong shape, a tensor of another architecture.
    let cfg_bytes = serde_json::to_vec(&cfg).unwrap();
    let mut w2 = w.clone();
    w2.remove("trunk.1.ln.bias");
    let e = Verifier::from_bytes(&cfg_bytes, &w2.to_safetensors().unwrap()).err().unwrap();
    assert!(matches!(&e, VerifierError::MissingTensor { name } if name == "trunk.1.ln.bias"), "{e}");
    let mut w3 = w.clone();
    w3.insert("act_enc.0.weight", vec![64, 15], vec![0.0; 64 * 15]).unwrap();
    let e = Verifier::from_bytes(&cfg_bytes, &w3.to_safetensors().unwrap()).err().unwrap();
    assert!(matches!(&e, VerifierError::TensorShape { name, .. } if name == "act_enc.0.weight"), "{e}");
    let mut w4 = w.clone();
    w4.insert("obs_in_ln.weight", vec![4], vec![1.0; 4]).unwrap();
    let e = Verifier::from_bytes(&cfg_bytes, &w4.to_safetensors().unwrap()).err().unwrap();
    assert!(matches!(&e, VerifierError::UnexpectedTensor { name } if name == "obs_in_ln.weight"), "{e}");
    // Inconsistent dimensions, odd step embedding, bad statistics, bad JSON.
    for (path, val) in [
        ("/input/act_dim", serde_json::json!(15)),
        ("/architecture/t_embed_dim", serde_json::json!(63)),
        ("/input/obs_std", serde_json::json!([1.0, 0.0, 1.0, 1.0])),
        ("/input/obs_mean", serde_json::json!([1.0])),
        ("/input/action_space", serde_json::json!({"space": "policy", "scale": [1.0, 0.0]})),
        ("/input/action_space", serde_json::json!({"space": "policy", "scale": [1.0, 1.0, 1.0]})),
    ] {
        let mut c = cfg_json();
        *c.pointer_mut(path).unwrap() = val.clone();
        let r = Verifier::from_bytes(&serde_json::to_vec(&c).unwrap(), &st);
        assert!(matches!(r, Err(VerifierError::Config(_))), "{path} = {val}: {:?}", r.err());
    }
    assert!(matches!(Verifier::from_bytes(b"{", &st), Err(VerifierError::Config(_))));
    // A non-finite weight.
    let mut w5 = w.clone();
    let mut head = w5.get("head.bias").unwrap().clone();
    head.data[0] = f32::INFINITY;
    w5.insert("head.bias", head.shape, head.data).unwrap();
    assert!(matches!(
        Verifier::from_bytes(&cfg_bytes, &w5.to_safetensors().unwrap()),
        Err(VerifierError::Safetensors(_))
    ));
}

#[test]
fn artifacts_without_action_space_are_read_as_standardized() {
    // Artifacts written before `input.action_space` existed fed the raw chunk standardised with
    // act_mean/act_std; they keep loading and scoring that way.
    let (cfg, w) = RandomSpec { standardized: true, ..RandomSpec::nav() }.build(6);
    let mut c = serde_json::to_value(&cfg).unwrap();
    c["input"].as_object_mut().unwrap().remove("action_space");
    c["input"].as_object_mut().unwrap().remove("t_embed_dim");
    let old = ArtifactConfig::from_json(&serde_json::to_vec(&c).unwrap()).unwrap();
    assert_eq!(old.input.action_space, ActionSpace::Standardized);
    let v = Verifier::new(old, &w).unwrap();
    let now = Verifier::new(cfg, &w).unwrap();
    let obs = vec![0.4; v.obs_dim()];
    let chunk = vec![0.02; v.act_dim()];
    assert_eq!(v.score(&obs, &[1], &chunk, 1).unwrap(), now.score(&obs, &[1], &chunk, 1).unwrap());
}

#[test]
fn action_space_maps_raw_chunks_both_ways() {
    let s = ActionSpace::policy(vec![0.04, 2.0], vec![0.0, 1.0]);
    let mut c = vec![0.04, 3.0, -0.02, 1.0];
    s.raw_to_input(&mut c, 2);
    assert_eq!(c, vec![1.0, 1.0, -0.5, 0.0]);
    s.input_to_raw(&mut c, 2);
    assert!((c[0] - 0.04).abs() < 1e-7 && c[1] == 3.0 && (c[2] + 0.02).abs() < 1e-7 && c[3] == 1.0);
    let mut same = vec![5.0, 6.0];
    ActionSpace::Standardized.raw_to_input(&mut same, 2);
    ActionSpace::default().raw_to_input(&mut same, 2);
    assert_eq!(same, vec![5.0, 6.0]);
}
