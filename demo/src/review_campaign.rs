//! A simulated labeling campaign: a pool of the demo's rollouts whose
//! labels are "asked for" 50 at a time, in verifier-uncertainty order (the episodes the current
//! classifier scores nearest 0.5 first, what `GET /v1/episodes?order=uncertain` serves) or in
//! random order; after each batch the classifier is retrained on the labels so far and its AUROC
//! measured on held-out rollouts. `benches/review_campaign.rs` runs it on sim rollouts with the
//! real trainer; the loop itself is here, generic over the training, so a fast test covers it.

use anyhow::{bail, Result};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The order in which the campaign asks for labels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AskOrder {
    /// The unlabeled episodes the current verifier scores nearest 0.5 first (ties by index).
    Uncertain,
    /// A fixed random permutation (the same seed gives both orders the same first labels).
    Random,
}

/// One point of the learning curve: the verifier trained on `labels` labels.
#[derive(Debug, Clone, PartialEq)]
pub struct CurvePoint {
    pub labels: usize,
    /// Held-out AUROC (`None` when undefined: one class held out).
    pub auroc: Option<f64>,
}

/// The campaign's shape.
#[derive(Debug, Clone)]
pub struct Campaign {
    /// Episodes that may be labeled (indices `0..pool`).
    pub pool: usize,
    /// Random labels to start from (a verifier needs some before it can order anything).
    pub start: usize,
    /// Labels per round (the 50).
    pub batch: usize,
    /// Stop after this many labels.
    pub budget: usize,
    pub seed: u64,
}

/// Runs the campaign. `fit(labeled)` trains a verifier on the pool episodes `labeled` and returns
/// its mean score of every pool episode (`pool` values) and its held-out AUROC.
pub fn run(
    c: &Campaign,
    order: AskOrder,
    mut fit: impl FnMut(&[usize]) -> Result<(Vec<f64>, Option<f64>)>,
) -> Result<Vec<CurvePoint>> {
    if c.start == 0 || c.batch == 0 || c.start > c.pool {
        bail!("a campaign needs 0 < start <= pool and batch > 0");
    }
    let mut rng = ChaCha8Rng::seed_from_u64(c.seed);
    let mut unlabeled: Vec<usize> = (0..c.pool).collect();
    unlabeled.shuffle(&mut rng);
    let mut labeled: Vec<usize> = unlabeled.drain(..c.start).collect();
    let mut curve = Vec::new();
    loop {
        let (scores, auroc) = fit(&labeled)?;
        if scores.len() != c.pool {
            bail!("fit returned {} scores for a pool of {}", scores.len(), c.pool);
        }
        curve.push(CurvePoint { labels: labeled.len(), auroc });
        if labeled.len() >= c.budget || unlabeled.is_empty() {
            return Ok(curve);
        }
        if order == AskOrder::Uncertain {
            let dist = |i: &usize| (scores[*i] - 0.5).abs();
            unlabeled.sort_by(|a, b| dist(a).total_cmp(&dist(b)).then(a.cmp(b)));
        }
        let take = c.batch.min(unlabeled.len()).min(c.budget - labeled.len());
        labeled.extend(unlabeled.drain(..take));
    }
}

/// The curve as a table: labels, AUROC per order.
pub fn table(uncertain: &[CurvePoint], random: &[CurvePoint]) -> String {
    let f = |a: Option<f64>| a.map(|x| format!("{x:.3}")).unwrap_or_else(|| "-".into());
    let mut s = String::from("labels  AUROC uncertain-first  AUROC random\n");
    for (u, r) in uncertain.iter().zip(random) {
        s.push_str(&format!("{:>6}  {:>21}  {:>12}\n", u.labels, f(u.auroc), f(r.auroc)));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stand-in verifier whose scores are fixed: the uncertain order must ask for the
    /// episodes nearest 0.5 first, and both orders see the same start and curve lengths.
    #[test]
    fn uncertain_order_asks_nearest_half_first() {
        let pool = 200;
        let scores: Vec<f64> = (0..pool).map(|i| (i as f64 * 0.618).fract()).collect();
        let c = Campaign { pool, start: 20, batch: 50, budget: 120, seed: 7 };
        let mut asked: Vec<Vec<usize>> = Vec::new();
        let curve = run(&c, AskOrder::Uncertain, |l| {
            asked.push(l.to_vec());
            Ok((scores.clone(), Some(l.len() as f64 / 1000.0)))
        })
        .unwrap();
        assert_eq!(curve.iter().map(|p| p.labels).collect::<Vec<_>>(), vec![20, 70, 120]);
        let first = &asked[0];
        let batch: Vec<usize> = asked[1][20..].to_vec();
        let mut rest: Vec<usize> = (0..pool).filter(|i| !first.contains(i)).collect();
        rest.sort_by(|a, b| (scores[*a] - 0.5).abs().total_cmp(&(scores[*b] - 0.5).abs()).then(a.cmp(b)));
        assert_eq!(batch, rest[..50].to_vec(), "the 50 nearest 0.5 among the unlabeled");
        let mut random_first = None;
        let rc = run(&c, AskOrder::Random, |l| {
            random_first.get_or_insert_with(|| l.to_vec());
            Ok((scores.clone(), None))
        })
        .unwrap();
        assert_eq!(random_first.unwrap(), *first, "the same random start for both orders");
        assert_eq!(rc.len(), 3);
        assert!(table(&curve, &rc).lines().count() == 4);
        assert!(run(&Campaign { start: 0, ..c }, AskOrder::Random, |_| Ok((vec![], None))).is_err());
    }
}
