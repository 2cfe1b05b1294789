//! Steering telemetry: what a best-of-N step saw and chose, recorded on the robot and kept with
//! the episode, so a later verifier or a smaller N can be tried on the same candidates without
//! running the robot (`ufops replay`).
//!
//! A [`SteeringStep`] is one re-planning step: the N candidate chunks as the policy sampled them
//! (raw actions, `H x A` each), their scores, the chosen index, the artifact that scored them
//! and the scoring latency. Candidates are stored as IEEE half floats; the recorder rounds them
//! to that grid *before* scoring ([`round_to_f16`]), so the stored candidates are exactly the
//! ones scored and executed and a replay with the same artifact reproduces every choice bit for
//! bit. Half precision keeps 11 significant bits (relative error ≤ 2^-11 ≈ 4.9e-4), far below any
//! robot's actuation noise, and halves the bytes of the largest part of the record.
//!
//! The column the store keeps them in is `store::steps::STEERING_COLUMN`; its encoding is
//! `steps::steering_array` / `steps::steering_log` (feature `steps`).

use half::f16;

/// One best-of-N step of a steered episode.
#[derive(Clone, Debug, PartialEq)]
pub struct SteeringStep {
    /// The episode step whose chunk this step chose (the row of the episode's steps).
    pub t: u32,
    /// The id of the verifier artifact that scored the candidates.
    pub artifact_id: String,
    /// The candidate chunks, raw actions, `n * chunk_len` values on the f16 grid.
    pub candidates: Vec<f32>,
    /// One score per candidate (`n`).
    pub scores: Vec<f32>,
    /// Index of the executed candidate.
    pub chosen: u32,
    /// Wall time of scoring the candidates, in microseconds.
    pub latency_us: u32,
}

impl SteeringStep {
    /// N, the number of candidates.
    pub fn n(&self) -> usize {
        self.scores.len()
    }

    /// Values per candidate (`H * A`), or 0 without candidates.
    pub fn chunk_len(&self) -> usize {
        self.candidates.len().checked_div(self.scores.len()).unwrap_or(0)
    }

    /// Checks the record's own consistency: candidates a multiple of the scores, the chosen
    /// index among them.
    pub fn check(&self) -> Result<(), String> {
        let n = self.scores.len();
        if n == 0 {
            return Err(format!("steering step at t={} has no candidates", self.t));
        }
        if !self.candidates.len().is_multiple_of(n) || self.candidates.is_empty() {
            return Err(format!(
                "steering step at t={}: {} candidate values for {n} scores",
                self.t,
                self.candidates.len()
            ));
        }
        if self.chosen as usize >= n {
            return Err(format!(
                "steering step at t={}: chosen index {} of {n} candidates",
                self.t, self.chosen
            ));
        }
        Ok(())
    }
}

/// Rounds every value to the nearest IEEE half float (the storage grid of candidates), in place.
/// Values beyond the half range become ±infinity, as they would in storage.
pub fn round_to_f16(values: &mut [f32]) {
    for v in values {
        *v = f16::from_f32(*v).to_f32();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_is_idempotent_and_close() {
        let mut v: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.137).sin() * 3.0).collect();
        let orig = v.clone();
        round_to_f16(&mut v);
        for (a, b) in v.iter().zip(&orig) {
            assert!((a - b).abs() <= b.abs() * 4.9e-4 + 6e-8, "{a} vs {b}");
        }
        let again: Vec<f32> = v.iter().map(|&x| f16::from_f32(x).to_f32()).collect();
        assert_eq!(again, v, "values on the f16 grid survive storage exactly");
    }

    #[test]
    fn check_names_the_problem() {
        let s = SteeringStep {
            t: 3,
            artifact_id: "a".into(),
            candidates: vec![0.0; 6],
            scores: vec![0.1, 0.2, 0.3],
            chosen: 3,
            latency_us: 5,
        };
        assert!(s.check().unwrap_err().contains("chosen index 3 of 3"));
        assert_eq!(SteeringStep { chosen: 2, ..s.clone() }.check(), Ok(()));
        assert_eq!(s.chunk_len(), 2);
        assert!(SteeringStep { candidates: vec![0.0; 5], chosen: 0, ..s }.check().is_err());
    }
}
