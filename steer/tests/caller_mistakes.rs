//! The robot-side client never panics on a caller's mistake: each one is an error that names it.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use steer::{
    best_of_n, best_of_n_raw, ddpm_sample, ddpm_sample_guided, flow_sample, ActionAffine, DdpmSchedule,
    Guidance, NoisePredictor, Result, Scorer, VelocityField,
};

/// Scores every chunk by its first value; the gradient has `grad_len` values per chunk.
struct First {
    ad: usize,
    grad_len: usize,
}
impl Scorer for First {
    fn obs_dim(&self) -> usize {
        1
    }
    fn act_dim(&self) -> usize {
        self.ad
    }
    fn score_batch(&self, _o: &[f32], _t: &[u32], c: &[f32], _n: usize) -> Result<Vec<f32>> {
        Ok(c.chunks(self.ad).map(|x| x[0]).collect())
    }
    fn grad_batch(&self, _o: &[f32], t: &[u32], _c: &[f32]) -> Result<Vec<f32>> {
        Ok(vec![1.0; t.len() * self.grad_len])
    }
}

/// eps = 0, with a caller-chosen action affine.
struct Zero {
    sched: DdpmSchedule,
    affine: Option<ActionAffine>,
}
impl NoisePredictor for Zero {
    fn obs_dim(&self) -> usize {
        1
    }
    fn act_dim(&self) -> usize {
        2
    }
    fn schedule(&self) -> &DdpmSchedule {
        &self.sched
    }
    fn predict_noise(&self, _o: &[f32], a: &[f32], _k: usize) -> Result<Vec<f32>> {
        Ok(vec![0.0; a.len()])
    }
    fn action_affine(&self) -> Option<ActionAffine> {
        self.affine.clone()
    }
}
impl VelocityField for Zero {
    fn obs_dim(&self) -> usize {
        1
    }
    fn act_dim(&self) -> usize {
        2
    }
    fn velocity(&self, _o: &[f32], a: &[f32], _t: f32) -> Result<Vec<f32>> {
        Ok(vec![0.0; a.len()])
    }
    fn action_affine(&self) -> Option<ActionAffine> {
        self.affine.clone()
    }
}

fn err_text<T: std::fmt::Debug>(r: Result<T>) -> String {
    r.expect_err("a caller mistake must be an error").to_string()
}

#[test]
fn best_of_n_with_no_candidates_is_an_error() {
    let s = First { ad: 2, grad_len: 2 };
    assert!(err_text(best_of_n(&s, &[0.0], &[0], &[], 0)).contains("n = 0"));
    assert!(err_text(best_of_n_raw(&s, None, &[0.0], &[0], &[], 0)).contains("n = 0"));
}

#[test]
fn an_empty_or_broken_action_affine_is_an_error() {
    let sched = || DdpmSchedule::from_betas(vec![0.2, 0.3]).unwrap();
    for (affine, what) in [
        (ActionAffine { scale: vec![], offset: vec![] }, "0 scales"),
        (ActionAffine { scale: vec![1.0], offset: vec![] }, "0 offsets"),
        (ActionAffine { scale: vec![1.0, 1.0, 1.0], offset: vec![0.0; 3] }, "not whole actions"),
        (ActionAffine { scale: vec![0.0, 1.0], offset: vec![0.0; 2] }, "non-zero"),
    ] {
        let p = Zero { sched: sched(), affine: Some(affine.clone()) };
        let rng = || ChaCha8Rng::seed_from_u64(1);
        assert!(err_text(ddpm_sample(&p, &[0.0], &mut rng())).contains(what), "ddpm: {what}");
        assert!(err_text(flow_sample(&p, &[0.0], &mut rng())).contains(what), "flow: {what}");
        let s = First { ad: 2, grad_len: 2 };
        assert!(err_text(best_of_n_raw(&s, Some(&affine), &[0.0], &[0], &[0.5, 0.5], 1)).contains(what));
        assert!(err_text(affine.apply(&mut [0.0, 0.0])).contains(what));
    }
}

#[test]
fn a_gradient_of_the_wrong_length_is_an_error() {
    let p = Zero { sched: DdpmSchedule::from_betas(vec![0.2, 0.3]).unwrap(), affine: None };
    let s = First { ad: 2, grad_len: 1 };
    let g = Guidance { scorer: &s, obs: &[0.0], t: &[0], lambda: 0.1 };
    let e = err_text(ddpm_sample_guided(&p, &[0.0], &g, &mut ChaCha8Rng::seed_from_u64(1)));
    assert!(e.contains("1 gradient values, expected 2"), "{e}");
}

#[test]
fn an_empty_or_invalid_schedule_is_an_error() {
    assert!(err_text(DdpmSchedule::from_betas(vec![])).contains("at least one step"));
    assert!(err_text(DdpmSchedule::squaredcos_cap_v2(0)).contains("at least one step"));
    assert!(err_text(DdpmSchedule::linear(0, 1e-4, 0.02)).contains("at least one step"));
    assert!(err_text(DdpmSchedule::from_betas(vec![0.1, 1.0])).contains("step 2"));
    assert!(err_text(DdpmSchedule::from_betas(vec![f64::NAN])).contains("not in (0, 1)"));
}
