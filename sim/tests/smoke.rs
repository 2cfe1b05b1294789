#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sim::env::Gap;
use sim::plot::{plot_panels, Panel};
use sim::*;
use steer::verifier::testutil::RandomSpec;
use steer::verifier::ArtifactFiles;
use steer::Verifier;

#[test]
fn demos_use_both_gaps_and_succeed() {
    let env = EnvConfig::default();
    let demos = expert_demos(&env, 20, 3);
    assert_eq!(demos.iter().filter(|d| d.wide).count(), 10);
    for d in &demos {
        assert_eq!(d.positions.len(), d.actions.len() + 1);
        assert!(env.in_goal(*d.positions.last().unwrap()));
        let g = env.gap_of(&d.positions).unwrap();
        assert_eq!(g == Gap::Wide, d.wide);
        for a in &d.actions {
            assert!((a[0] * a[0] + a[1] * a[1]).sqrt() <= env.max_speed + 1e-6);
        }
    }
}

fn check_episodes(eps: &[Episode], h: usize) {
    for e in eps {
        assert_eq!(e.positions.len(), e.length + 1);
        assert_eq!(e.actions.len(), e.length);
        assert_eq!(e.action_chunks.len(), e.length);
        assert!(e.action_chunks.iter().all(|c| c.len() == h * 2));
        assert_eq!(e.chunk_offset[0], 0);
        assert!(e.length >= 1);
    }
}

#[test]
fn policies_train_sample_and_roll_out_with_every_steering() {
    let env = EnvConfig::default();
    let demos = expert_demos(&env, 20, 0);
    let pc = PolicyConfig { hidden: 64, depth: 2, diffusion_steps: 10, flow_steps: 5, ..Default::default() };
    let tc = PolicyTrainConfig { steps: 150, batch: 128, ..Default::default() };
    let ddpm = DiffusionPolicy::train(&pc, &tc, &demos).unwrap();
    let flow = FlowPolicy::train(&pc, &tc, &demos).unwrap();
    assert!(ddpm.train_loss.is_finite() && flow.train_loss.is_finite());
    // a random-weights verifier with the nav dimensions, through the artifact path
    let dir = tempfile::tempdir().unwrap();
    let (cfg, w) = RandomSpec::nav().build(1);
    ArtifactFiles::build(&cfg, &w).unwrap().write_dir(dir.path()).unwrap();
    let v = Verifier::load_dir(dir.path()).unwrap();
    let small = EnvConfig { max_steps: 24, ..env.clone() };
    for p in [&ddpm as &dyn ChunkPolicy, &flow as &dyn ChunkPolicy] {
        for s in [
            ChunkChoice::None,
            ChunkChoice::BestOfN { scorer: &v, n: 4 },
            ChunkChoice::Guided { scorer: &v, lambda: 0.01 },
        ] {
            let eps = rollout(p, &small, 6, s, 5).unwrap();
            assert_eq!(eps.len(), 6);
            check_episodes(&eps, pc.horizon);
            // seeded: identical on a re-run
            let again = rollout(p, &small, 6, s, 5).unwrap();
            assert_eq!(eps[0].positions, again[0].positions, "{} {}", p.name(), s.label());
        }
        // same seed, base vs steered: same start positions
        let a = rollout(p, &small, 3, ChunkChoice::None, 9).unwrap();
        let b = rollout(p, &small, 3, ChunkChoice::BestOfN { scorer: &v, n: 3 }, 9).unwrap();
        assert_eq!(a[2].positions[0], b[2].positions[0]);
    }
    // save / load round trip gives identical samples
    let d2 = tempfile::tempdir().unwrap();
    ddpm.save(d2.path()).unwrap();
    let re = DiffusionPolicy::load(d2.path()).unwrap();
    let obs = [0.1f32, 0.5, 0.1, 0.5];
    let s1 = steer::ddpm_sample(&ddpm, &obs, &mut ChaCha8Rng::seed_from_u64(2)).unwrap();
    let s2 = steer::ddpm_sample(&re, &obs, &mut ChaCha8Rng::seed_from_u64(2)).unwrap();
    assert_eq!(s1, s2);
    // plot
    let eps = rollout(&ddpm, &small, 4, ChunkChoice::None, 1).unwrap();
    let png = dir.path().join("t.png");
    plot_panels(
        &png,
        &env,
        &[Panel::from_demos("demos", &demos, 10), Panel::from_episodes("base", &eps, 10)],
        120,
    )
    .unwrap();
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
}
