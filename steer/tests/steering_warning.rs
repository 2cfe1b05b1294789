//! A verifier whose training flagged it as unlikely to steer well (its action-sensitivity figure,
//! `verifier::quality`) is named once per process by the best-of-N helpers, not once per step;
//! an unflagged one, or one trained before the figure existed, is never named.

use steer::{best_of_n, warn_if_flagged, Verifier};
use verifier::testutil::RandomSpec;
use verifier::ActionSensitivity;

/// A random verifier whose metrics carry the figure with this action AUROC (`None`: no figure).
fn verifier_with(action_auc: Option<f64>) -> Verifier {
    let (mut config, weights) = RandomSpec::nav().build(7);
    if let Some(a) = action_auc {
        let figure = ActionSensitivity {
            obs_only_auc: Some(0.9),
            auc_gain: Some(0.004),
            action_auc: Some(a),
            strata: 10,
            unsure_fraction: 0.2,
            unsure_auc: None,
            unsure_obs_only_auc: None,
            flagged: false,
            reason: None,
            twin_seconds: 1.0,
        }
        .flag();
        config.metrics = serde_json::json!({ "final": { "action_sensitivity": figure } });
    }
    Verifier::new(config, &weights).unwrap()
}

#[test]
fn a_flagged_verifier_is_named_once_and_an_unflagged_one_never() {
    let flagged = verifier_with(Some(0.412));
    let warning = flagged.steering_warning().expect("flagged below the floor");
    assert!(warning.contains("0.41 AUROC") && warning.contains("observation-only twin"), "{warning}");
    assert!(warn_if_flagged(&flagged), "the first use warns");
    assert!(!warn_if_flagged(&flagged), "... and only the first");

    // best-of-N warns through the same gate: after it ran, the gate has already warned.
    let other = verifier_with(Some(0.433));
    let (od, ad) = (other.obs_dim(), other.act_dim());
    let picked = best_of_n(&other, &vec![0.1; od], &[3], &vec![0.2; 4 * ad], 4).unwrap();
    assert_eq!(picked.index.len(), 1);
    assert!(!warn_if_flagged(&other), "best_of_n warned already");

    for quiet in [verifier_with(Some(0.8)), verifier_with(None)] {
        assert_eq!(quiet.steering_warning(), None);
        assert!(!warn_if_flagged(&quiet));
    }
}
