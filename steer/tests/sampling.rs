use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use steer::{
    best_of_n, ddpm_sample, ddpm_sample_guided, flow_sample, flow_sample_guided, select_best, DdpmSchedule,
    Guidance, NoisePredictor, Result, Scorer, VelocityField,
};

/// eps(s, a, k) = c[k] * a + 0.1 * s   (obs_dim = act_dim)
struct LinEps {
    sched: DdpmSchedule,
    c: Vec<f32>,
    ad: usize,
    clip: Option<f32>,
}
impl NoisePredictor for LinEps {
    fn obs_dim(&self) -> usize {
        self.ad
    }
    fn act_dim(&self) -> usize {
        self.ad
    }
    fn schedule(&self) -> &DdpmSchedule {
        &self.sched
    }
    fn predict_noise(&self, obs: &[f32], a: &[f32], k: usize) -> Result<Vec<f32>> {
        Ok(a.iter().zip(obs).map(|(a, s)| self.c[k] * a + 0.1 * s).collect())
    }
    fn clip_sample(&self) -> Option<f32> {
        self.clip
    }
}

/// v(s, a, t) = (0.5 + t) * a - s
struct LinVel {
    ad: usize,
    steps: usize,
}
impl VelocityField for LinVel {
    fn obs_dim(&self) -> usize {
        self.ad
    }
    fn act_dim(&self) -> usize {
        self.ad
    }
    fn velocity(&self, obs: &[f32], a: &[f32], t: f32) -> Result<Vec<f32>> {
        Ok(a.iter().zip(obs).map(|(a, s)| (0.5 + t) * a - s).collect())
    }
    fn num_steps(&self) -> usize {
        self.steps
    }
}

/// log C(a) = -|a - target|^2 / 2  ->  grad = target - a; score = exp(log C)
struct Quad {
    target: Vec<f32>,
}
impl Scorer for Quad {
    fn obs_dim(&self) -> usize {
        1
    }
    fn act_dim(&self) -> usize {
        self.target.len()
    }
    fn score_batch(&self, _o: &[f32], t: &[u32], c: &[f32], n: usize) -> Result<Vec<f32>> {
        let ad = self.target.len();
        Ok((0..t.len() * n)
            .map(|i| {
                let d: f32 = (0..ad).map(|j| (c[i * ad + j] - self.target[j]).powi(2)).sum();
                (-0.5 * d).exp()
            })
            .collect())
    }
    fn grad_batch(&self, _o: &[f32], _t: &[u32], c: &[f32]) -> Result<Vec<f32>> {
        let ad = self.target.len();
        Ok(c.iter().enumerate().map(|(i, a)| self.target[i % ad] - a).collect())
    }
}

#[test]
fn squaredcos_schedule_values() {
    // diffusers DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2")
    let s = DdpmSchedule::squaredcos_cap_v2(100).unwrap();
    let close = |a: f64, b: f64| assert!((a - b).abs() < 1e-9 * b.abs().max(1e-3), "{a} vs {b}");
    close(s.beta(1), 0.0006312815983416931);
    close(s.beta(50), 0.030593124281670048);
    close(s.beta(99), 0.7499392803846627);
    close(s.beta(100), 0.999); // capped at max_beta
    close(s.alpha_bar(1), 0.9993687184016583);
    close(s.alpha_bar(50), 0.49384359044063775);
    close(s.alpha_bar(100), 2.4285722793500615e-07);
    assert_eq!(s.alpha_bar(0), 1.0);
    let s2 = DdpmSchedule::squaredcos_cap_v2(2).unwrap();
    close(s2.beta(1), 0.5061564095593623);
    close(s2.beta(2), 0.999);
}

/// Algorithm 2 with K = 2, hand-computed.
#[test]
fn ddpm_guidance_two_step_hand_computed() {
    let p = LinEps {
        sched: DdpmSchedule::from_betas(vec![0.1, 0.5]).unwrap(),
        c: vec![0.25, 0.5],
        ad: 1,
        clip: None,
    };
    let q = Quad { target: vec![2.0] };
    let obs = [0.3f32];
    let lam = 0.4f64;
    let g = Guidance { scorer: &q, obs: &[0.0], t: &[0], lambda: lam as f32 };
    let seed = 11;
    let out = ddpm_sample_guided(&p, &obs, &g, &mut ChaCha8Rng::seed_from_u64(seed)).unwrap();
    // the same random draws: a_2, then z for k = 2 (none for k = 1)
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let draw =
        |r: &mut ChaCha8Rng| -> f64 { rand::Rng::sample::<f32, _>(r, rand_distr::StandardNormal) as f64 };
    let a2 = draw(&mut rng);
    let z = draw(&mut rng);
    let s = 0.3f64;
    // k = 2: alpha_bar_2 = 0.9 * 0.5 = 0.45, alpha_bar_1 = 0.9, beta_2 = 0.5, alpha_2 = 0.5
    let eps = 0.5 * a2 + 0.1 * s;
    let x0 = (a2 - 0.55f64.sqrt() * eps) / 0.45f64.sqrt();
    let x0 = x0 + lam * (2.0 - x0);
    let mu = 0.9f64.sqrt() * 0.5 / 0.55 * x0 + 0.5f64.sqrt() * 0.1 / 0.55 * a2;
    let a1 = mu + (0.1 / 0.55 * 0.5f64).sqrt() * z;
    // k = 1: alpha_bar_1 = 0.9, alpha_bar_0 = 1, beta_1 = 0.1 -> mu = x0_hat (coefficient 1, 0)
    let eps = 0.25 * a1 + 0.1 * s;
    let x0 = (a1 - 0.1f64.sqrt() * eps) / 0.9f64.sqrt();
    let a0 = x0 + lam * (2.0 - x0);
    assert!((out[0] as f64 - a0).abs() < 1e-5, "{} vs {a0}", out[0]);
}

#[test]
fn flow_guidance_two_step_hand_computed() {
    let p = LinVel { ad: 1, steps: 2 };
    let q = Quad { target: vec![1.5] };
    let lam = 0.3f64;
    let g = Guidance { scorer: &q, obs: &[0.0], t: &[0], lambda: lam as f32 };
    let out = flow_sample_guided(&p, &[0.2], &g, &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
    let a1: f64 =
        rand::Rng::sample::<f32, _>(&mut ChaCha8Rng::seed_from_u64(5), rand_distr::StandardNormal) as f64;
    // step 0 (t = 1): no guidance
    let x = a1 - 0.5 * (1.5 * a1 - 0.2);
    // step 1 (t = 0.5): x0 = x - 0.5 v, x0' = x0 + lam (1.5 - x0), v' = (x - x0') / 0.5, x -= 0.5 v'
    let v = 1.0 * x - 0.2;
    let x0 = x - 0.5 * v;
    let x0p = x0 + lam * (1.5 - x0);
    let want = x - 0.5 * ((x - x0p) / 0.5);
    assert!((out[0] as f64 - want).abs() < 1e-5, "{} vs {want}", out[0]);
    // unguided differs
    let un = flow_sample(&p, &[0.2], &mut ChaCha8Rng::seed_from_u64(5)).unwrap();
    assert!((un[0] as f64 - (x - 0.5 * v)).abs() < 1e-5);
}

#[test]
fn lambda_zero_reproduces_unguided() {
    let ad = 6;
    let p = LinEps {
        sched: DdpmSchedule::squaredcos_cap_v2(20).unwrap(),
        c: (0..20).map(|k| 0.1 + 0.04 * k as f32).collect(),
        ad,
        clip: Some(1.0),
    };
    let obs: Vec<f32> = (0..3 * ad).map(|i| (i as f32 * 0.37).sin()).collect();
    let q = Quad { target: vec![0.5; ad] };
    let gobs = [0.0f32; 3];
    let t = [0u32, 4, 8];
    let un = ddpm_sample(&p, &obs, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    let g0 = Guidance { scorer: &q, obs: &gobs, t: &t, lambda: 0.0 };
    let gu = ddpm_sample_guided(&p, &obs, &g0, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    assert_eq!(un, gu);
    let g1 = Guidance { lambda: 0.5, ..g0 };
    let gu1 = ddpm_sample_guided(&p, &obs, &g1, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    assert_ne!(un, gu1);
    // guidance pulls towards the target
    let dist = |x: &[f32]| x.iter().map(|v| (v - 0.5).abs()).sum::<f32>();
    assert!(dist(&gu1) < dist(&un));

    let f = LinVel { ad, steps: 10 };
    let un = flow_sample(&f, &obs, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    let gu = flow_sample_guided(&f, &obs, &g0, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    assert_eq!(un, gu);
    let gu1 = flow_sample_guided(&f, &obs, &g1, &mut ChaCha8Rng::seed_from_u64(9)).unwrap();
    assert!(dist(&gu1) < dist(&un));
}

#[test]
fn best_of_n_picks_the_argmax() {
    let q = Quad { target: vec![1.0, -1.0] };
    // 2 groups x 4 candidates
    let c = vec![
        0.0, 0.0, 1.0, -0.9, 5.0, 5.0, 1.0, 1.0, // group 0: best is #1
        3.0, 3.0, 2.0, 2.0, 0.9, -1.2, 1.0, -1.0, // group 1: best is #3
    ];
    let r = best_of_n(&q, &[0.0, 0.0], &[0, 1], &c, 4).unwrap();
    assert_eq!(r.index, vec![1, 3]);
    assert_eq!(r.chunks, vec![1.0, -0.9, 1.0, -1.0]);
    assert_eq!(r.scores.len(), 8);
    assert_eq!(select_best(&[f32::NAN, 0.1, 0.3, 0.3]), 2);
    assert_eq!(select_best(&[-1.0]), 0);
}

/// Algorithm 2 adds the gradient step to x̂0 and uses it as it is: the clip the policy applies to
/// its own x̂0 (diffusers' clip_sample) is not applied again after the step.
#[test]
fn ddpm_guidance_does_not_clip_after_the_gradient_step() {
    // K = 1: alpha_bar_0 = 1, so the posterior mean is x̂0 itself and there is no noise.
    let p =
        LinEps { sched: DdpmSchedule::from_betas(vec![0.3]).unwrap(), c: vec![0.5], ad: 1, clip: Some(1.0) };
    let q = Quad { target: vec![5.0] };
    let lam = 0.5f64;
    let g = Guidance { scorer: &q, obs: &[0.0], t: &[0], lambda: lam as f32 };
    let out = ddpm_sample_guided(&p, &[0.3], &g, &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
    let a1: f64 =
        rand::Rng::sample::<f32, _>(&mut ChaCha8Rng::seed_from_u64(3), rand_distr::StandardNormal) as f64;
    let eps = 0.5 * a1 + 0.1 * 0.3;
    let x0 = ((a1 - 0.3f64.sqrt() * eps) / 0.7f64.sqrt()).clamp(-1.0, 1.0);
    let want = x0 + lam * (5.0 - x0);
    assert!((out[0] as f64 - want).abs() < 1e-5, "{} vs {want}", out[0]);
    assert!(out[0] > 1.0, "the guided x̂0 was clipped again: {}", out[0]);
}

/// A raw-action scorer (older verifiers) with a policy affine: the gradient is taken at
/// raw(x̂0) and mapped back by the chain rule; a policy-space scorer gets x̂0 itself.
#[test]
fn guidance_takes_the_gradient_in_the_space_the_scorer_takes() {
    struct Affine(LinEps);
    impl NoisePredictor for Affine {
        fn obs_dim(&self) -> usize {
            self.0.obs_dim()
        }
        fn act_dim(&self) -> usize {
            self.0.act_dim()
        }
        fn schedule(&self) -> &DdpmSchedule {
            self.0.schedule()
        }
        fn predict_noise(&self, obs: &[f32], a: &[f32], k: usize) -> Result<Vec<f32>> {
            self.0.predict_noise(obs, a, k)
        }
        fn action_affine(&self) -> Option<steer::ActionAffine> {
            Some(steer::ActionAffine { scale: vec![2.0], offset: vec![1.0] })
        }
    }
    struct RawQuad(Quad);
    impl Scorer for RawQuad {
        fn obs_dim(&self) -> usize {
            1
        }
        fn act_dim(&self) -> usize {
            1
        }
        fn takes_policy_space(&self) -> bool {
            false
        }
        fn score_batch(&self, o: &[f32], t: &[u32], c: &[f32], n: usize) -> Result<Vec<f32>> {
            self.0.score_batch(o, t, c, n)
        }
        fn grad_batch(&self, o: &[f32], t: &[u32], c: &[f32]) -> Result<Vec<f32>> {
            self.0.grad_batch(o, t, c)
        }
    }
    let p = Affine(LinEps {
        sched: DdpmSchedule::from_betas(vec![0.3]).unwrap(),
        c: vec![0.5],
        ad: 1,
        clip: None,
    });
    let lam = 0.1f64;
    let a1: f64 =
        rand::Rng::sample::<f32, _>(&mut ChaCha8Rng::seed_from_u64(4), rand_distr::StandardNormal) as f64;
    let x0 = (a1 - 0.3f64.sqrt() * (0.5 * a1 + 0.03)) / 0.7f64.sqrt();
    // Raw scorer, target 3 in raw units: d/dx log C(2x + 1) = 2 * (3 - (2 x0 + 1)).
    let raw = RawQuad(Quad { target: vec![3.0] });
    let g = Guidance { scorer: &raw, obs: &[0.0], t: &[0], lambda: lam as f32 };
    let out = ddpm_sample_guided(&p, &[0.3], &g, &mut ChaCha8Rng::seed_from_u64(4)).unwrap();
    let want = 2.0 * (x0 + lam * 2.0 * (3.0 - (2.0 * x0 + 1.0))) + 1.0;
    assert!((out[0] as f64 - want).abs() < 1e-4, "raw scorer: {} vs {want}", out[0]);
    // Policy-space scorer, target 1 in sample units: d/dx log C(x) = 1 - x0.
    let pol = Quad { target: vec![1.0] };
    let g = Guidance { scorer: &pol, obs: &[0.0], t: &[0], lambda: lam as f32 };
    let out = ddpm_sample_guided(&p, &[0.3], &g, &mut ChaCha8Rng::seed_from_u64(4)).unwrap();
    let want = 2.0 * (x0 + lam * (1.0 - x0)) + 1.0;
    assert!((out[0] as f64 - want).abs() < 1e-4, "policy-space scorer: {} vs {want}", out[0]);
}

#[test]
fn best_of_n_on_raw_candidates_scores_them_in_the_policy_space() {
    // Policy space x = (raw - 1) / 2; the scorer prefers x near 0.5, i.e. raw near 2.
    let q = Quad { target: vec![0.5] };
    let aff = steer::ActionAffine { scale: vec![2.0], offset: vec![1.0] };
    let raw = [0.5f32, 2.1, 1.5, 3.0];
    let r = steer::best_of_n_raw(&q, Some(&aff), &[0.0], &[0], &raw, 4).unwrap();
    assert_eq!(r.index, vec![1]);
    assert_eq!(r.chunks, vec![2.1]);
    // Scored as they are, the same scorer would pick raw 0.5.
    assert_eq!(best_of_n(&q, &[0.0], &[0], &raw, 4).unwrap().index, vec![0]);
}
