//! Scalar functions of the contract: the step embedding, the sigmoid, and the exact GELU.

/// Sinusoidal episode-step embedding (the paper's eq. 1, ARTIFACT.md): `sin(t / 10000^(j/d))`
/// for even `j`, `cos(t / 10000^((j-1)/d))` for odd `j`, `d = out.len()`. Computed in f64,
/// rounded to f32.
pub fn time_embedding_into(t: f64, out: &mut [f32]) {
    let d = out.len() as f64;
    for (j, o) in out.iter_mut().enumerate() {
        let e = (j - (j % 2)) as f64 / d;
        let arg = t / 10000f64.powf(e);
        *o = if j % 2 == 0 { arg.sin() } else { arg.cos() } as f32;
    }
}

/// Numerically stable logistic sigmoid.
pub fn sigmoid(y: f32) -> f32 {
    if y >= 0.0 {
        1.0 / (1.0 + (-y).exp())
    } else {
        let e = y.exp();
        e / (1.0 + e)
    }
}

/// Exact GELU `x * Phi(x)`, in f64.
pub(crate) fn gelu(x: f32) -> f32 {
    let x = x as f64;
    (0.5 * x * (1.0 + libm::erf(x * std::f64::consts::FRAC_1_SQRT_2))) as f32
}

/// `d gelu / dx = Phi(x) + x * phi(x)`, in f64.
pub(crate) fn gelu_grad(x: f32) -> f32 {
    let x = x as f64;
    let cdf = 0.5 * (1.0 + libm::erf(x * std::f64::consts::FRAC_1_SQRT_2));
    let pdf = (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
    (cdf + x * pdf) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedding_follows_the_contract() {
        let mut e = [0f32; 4];
        time_embedding_into(1.0, &mut e);
        let want = [1f64.sin(), 1f64.cos(), 0.01f64.sin(), 0.01f64.cos()];
        for j in 0..4 {
            assert!((e[j] as f64 - want[j]).abs() < 1e-7, "{j}");
        }
    }

    #[test]
    fn gelu_and_its_derivative() {
        // Reference values of x * Phi(x) (scipy.stats.norm.cdf).
        for (x, want) in [
            (0.0f32, 0.0f64),
            (1.0, 0.8413447460685429),
            (-1.0, -0.15865525393145707),
            (2.5, 2.4844758366855597),
        ] {
            assert!((gelu(x) as f64 - want).abs() < 1e-6, "gelu({x})");
        }
        for x in [-3.0f32, -0.7, 0.0, 0.4, 2.0] {
            let h = 1e-3f64;
            let fd = (gelu((x as f64 + h) as f32) as f64 - gelu((x as f64 - h) as f32) as f64) / (2.0 * h);
            assert!((fd - gelu_grad(x) as f64).abs() < 1e-3, "gelu'({x}): fd {fd}");
        }
        assert!((sigmoid(0.0) - 0.5).abs() < 1e-7 && sigmoid(-100.0) >= 0.0 && sigmoid(100.0) <= 1.0);
    }
}
