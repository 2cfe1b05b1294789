//! One network of a verifier ([`crate::Verifier`] holds one, or an ensemble's members): the
//! forward pass of ARTIFACT.md and its gradient w.r.t. the action chunk, for every variant (lowdim; features with input/encoder LayerNorm and exact GELU; extra inputs;
//! any trunk length), on weights packed once at load time.
//!
//! The observation side (observation encoder, step embedding, extra inputs and their columns
//! of `trunk.0`) is computed once per group of candidates, the action side once per
//! candidate; candidates of a group then meet in `trunk.0`. Matrix products go through the
//! packed kernel of [`crate::kernels`] (AVX2/FMA when the CPU has it).
//!
//! One file at 700 lines: the forward pass and its action gradient, read against each other.

use crate::error::{Result, VerifierError};
use crate::format::{Activation, ArtifactConfig, Kind};
use crate::kernels::{dot, gemm, ln_backward, ln_forward, ln_inplace, pad8, Isa, Packed};
use crate::math::{gelu, gelu_grad, sigmoid, time_embedding_into};
use crate::weights::Weights;

#[derive(Clone, Debug)]
struct Norm {
    g: Vec<f32>,
    b: Vec<f32>,
}

#[derive(Clone, Debug)]
struct EncLayer {
    fwd: Packed,
    bias: Vec<f32>,
    ln: Option<Norm>,
    /// An activation follows (after the LayerNorm, if any).
    act: bool,
    /// Input-gradient packing (action encoder only).
    bwd: Option<Packed>,
}

#[derive(Clone, Debug)]
struct TrunkLayer {
    d: usize,
    /// `trunk.l` for l >= 1 (`trunk.0` is split into `ctx` / `act` columns).
    fwd: Packed,
    bwd: Packed,
    bias: Vec<f32>,
    norm: Norm,
}

#[derive(Clone, Debug)]
struct Extra {
    dim: usize,
    width: usize,
    fwd: Packed,
    bias: Vec<f32>,
}

/// One loaded network (success classifier or time-to-success Q). Immutable after loading, so
/// it is `Send + Sync` and one instance serves any number of threads.
#[derive(Clone, Debug)]
pub(crate) struct Net {
    /// Extra inputs' names, for messages.
    extra_names: Vec<String>,
    isa: Isa,
    kind: Kind,
    activation: Activation,
    eps: f32,
    od: usize,
    ad: usize,
    ew: usize,
    td: usize,
    /// Width of the per-group context row `[ho, e, extras...]`.
    cw: usize,
    obs_mean: Vec<f32>,
    obs_inv_std: Vec<f32>,
    /// `(act_mean, 1 / act_std)`; `None` when the chunk is fed as it is (mean 0, std 1).
    act_norm: Option<(Vec<f32>, Vec<f32>)>,
    obs_in_ln: Option<Norm>,
    obs_enc: [EncLayer; 2],
    act_enc: [EncLayer; 2],
    extras: Vec<Extra>,
    trunk0_ctx: Packed,
    trunk0_act: Packed,
    trunk0_act_bwd: Packed,
    trunk: Vec<TrunkLayer>,
    head_w: Vec<f32>,
    head_b: f32,
    /// Zero rows for products without an initial value (widest padded width).
    zeros: Vec<f32>,
}

fn relu(x: f32) -> f32 {
    if x < 0.0 {
        0.0
    } else {
        x
    }
}

fn padded(v: &[f32]) -> Vec<f32> {
    let mut p = v.to_vec();
    p.resize(pad8(v.len()), 0.0);
    p
}

impl Net {
    /// The network whose tensors are named `{prefix}{name}` in `weights` (the caller has
    /// validated both against each other), with the given kernels.
    pub(crate) fn build(config: &ArtifactConfig, weights: &Weights, prefix: &str, isa: Isa) -> Result<Self> {
        let a = &config.architecture;
        let i = &config.input;
        let (od, ad, ew, td) = (i.obs_dim, i.act_dim, a.encoder_width, a.t_embed_dim);
        // Every tensor exists with its shape (validated above).
        let t = |n: &str| -> &[f32] {
            let name = format!("{prefix}{n}");
            weights.get(&name).map_or(&[][..], |w| w.data.as_slice())
        };
        let range = |a: usize, b: usize| (a..b).collect::<Vec<usize>>();
        let norm =
            |p: &str| Norm { g: t(&format!("{p}.weight")).to_vec(), b: t(&format!("{p}.bias")).to_vec() };
        let enc = |p: &str, inp: usize, backward: bool| -> [EncLayer; 2] {
            let layer = |l: usize, inp: usize| {
                let name = format!("{p}.{l}");
                let w = t(&format!("{name}.weight"));
                EncLayer {
                    fwd: Packed::forward(w, ew, inp, &range(0, inp)),
                    bias: padded(t(&format!("{name}.bias"))),
                    ln: a.encoder_layernorm.then(|| norm(&format!("{name}.ln"))),
                    act: a.encoder_activation_after(l),
                    bwd: backward.then(|| Packed::backward(w, ew, inp, &range(0, inp))),
                }
            };
            [layer(0, inp), layer(1, ew)]
        };
        let trunk_in = a.trunk_in();
        let t0 = a.trunk_dims[0];
        // trunk.0 input columns: [ho (ew), ha (ew), e (td), extras...]; the context is all but ha.
        let mut ctx_cols = range(0, ew);
        ctx_cols.extend(2 * ew..trunk_in);
        let w0 = t("trunk.0.weight");
        let mut trunk = Vec::new();
        let mut prev = t0;
        for (l, &d) in a.trunk_dims.iter().enumerate().skip(1) {
            let wl = t(&format!("trunk.{l}.weight"));
            trunk.push(TrunkLayer {
                d,
                fwd: Packed::forward(wl, d, prev, &range(0, prev)),
                bwd: Packed::backward(wl, d, prev, &range(0, prev)),
                bias: padded(t(&format!("trunk.{l}.bias"))),
                norm: norm(&format!("trunk.{l}.ln")),
            });
            prev = d;
        }
        let extras = a
            .extra_inputs
            .iter()
            .map(|e| {
                let p = format!("extra.{}", e.name);
                Extra {
                    dim: e.dim,
                    width: e.width,
                    fwd: Packed::forward(t(&format!("{p}.weight")), e.width, e.dim, &range(0, e.dim)),
                    bias: padded(t(&format!("{p}.bias"))),
                }
            })
            .collect();
        let trivial = i.act_mean.iter().all(|&m| m == 0.0) && i.act_std.iter().all(|&s| s == 1.0);
        let widest =
            [od, ad, ew, trunk_in].into_iter().chain(a.trunk_dims.iter().copied()).max().unwrap_or(0);
        let mut first = vec![TrunkLayer {
            d: t0,
            fwd: Packed::forward(&[], 0, 0, &[]),
            bwd: Packed::forward(&[], 0, 0, &[]),
            bias: padded(t("trunk.0.bias")),
            norm: norm("trunk.0.ln"),
        }];
        first.extend(trunk);
        Ok(Net {
            extra_names: a.extra_inputs.iter().map(|e| e.name.clone()).collect(),
            isa: isa.checked(),
            kind: config.kind,
            activation: a.activation,
            eps: a.layernorm_eps as f32,
            od,
            ad,
            ew,
            td,
            cw: trunk_in - ew,
            obs_mean: i.obs_mean.clone(),
            obs_inv_std: i.obs_std.iter().map(|s| 1.0 / s).collect(),
            act_norm: (!trivial).then(|| (i.act_mean.clone(), i.act_std.iter().map(|s| 1.0 / s).collect())),
            obs_in_ln: a.input_layernorm.then(|| norm("obs_in_ln")),
            obs_enc: enc("obs_enc", od, false),
            act_enc: enc("act_enc", ad, true),
            extras,
            trunk0_ctx: Packed::forward(w0, t0, trunk_in, &ctx_cols),
            trunk0_act: Packed::forward(w0, t0, trunk_in, &range(ew, 2 * ew)),
            trunk0_act_bwd: Packed::backward(w0, t0, trunk_in, &range(ew, 2 * ew)),
            trunk: first,
            head_w: t("head.weight").to_vec(),
            head_b: t("head.bias").first().copied().unwrap_or(0.0),
            zeros: vec![0.0; pad8(widest)],
        })
    }

    /// Scores of `n` candidates for each of `B = t.len()` observations into a buffer of `B * n`
    /// (classifier: sigmoid(logit), q: the value); shapes as [`crate::Verifier::score_ext`].
    pub(crate) fn score_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        candidates: &[f32],
        n: usize,
        out: &mut [f32],
    ) -> Result<()> {
        self.check(obs, extras, t, candidates, n, out.len())?;
        if out.is_empty() {
            return Ok(());
        }
        self.forward_y(obs, extras, t, candidates, n, out);
        if self.kind == Kind::Classifier {
            out.iter_mut().for_each(|y| *y = sigmoid(*y));
        }
        Ok(())
    }

    /// Guidance gradients of `B = t.len()` chunks into a buffer of `B * act_dim`: d log C / d
    /// chunk (classifier) or d Q / d chunk.
    pub(crate) fn grad_into(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        chunks: &[f32],
        out: &mut [f32],
    ) -> Result<()> {
        let b = t.len();
        self.check(obs, extras, t, chunks, 1, b)?;
        if out.len() != chunks.len() {
            return Err(VerifierError::Input(format!(
                "gradient buffer has length {}, expected {} (batch {b} * act_dim {})",
                out.len(),
                chunks.len(),
                self.ad
            )));
        }
        if b == 0 {
            return Ok(());
        }
        self.backward(obs, extras, t, chunks, out);
        Ok(())
    }

    fn check(
        &self,
        obs: &[f32],
        extras: &[&[f32]],
        t: &[u32],
        chunks: &[f32],
        n: usize,
        out_len: usize,
    ) -> Result<()> {
        let b = t.len();
        let bad = |m: String| Err(VerifierError::Input(m));
        if Some(obs.len()) != b.checked_mul(self.od) {
            return bad(format!("obs has length {}, expected batch {b} * obs_dim {}", obs.len(), self.od));
        }
        let want = b.checked_mul(n).and_then(|m| m.checked_mul(self.ad));
        if Some(chunks.len()) != want {
            return bad(format!(
                "candidates have length {}, expected batch {b} * n {n} * act_dim {}",
                chunks.len(),
                self.ad
            ));
        }
        if Some(out_len) != b.checked_mul(n) {
            return bad(format!("output buffer has length {out_len}, expected batch {b} * n {n}"));
        }
        let ex = &self.extras;
        if extras.len() != ex.len() {
            return bad(format!(
                "the verifier takes {} extra input(s) ({:?}), got {}",
                ex.len(),
                self.extra_names,
                extras.len()
            ));
        }
        for (e, (x, name)) in ex.iter().zip(extras.iter().zip(&self.extra_names)) {
            if Some(x.len()) != b.checked_mul(e.dim) {
                return bad(format!(
                    "extra input {:?} has length {}, expected batch {b} * dim {}",
                    name,
                    x.len(),
                    e.dim
                ));
            }
        }
        Ok(())
    }

    #[allow(clippy::too_many_arguments)] // a kernel's operands: raw pointers and their strides
    fn gemm(
        &self,
        x: &[f32],
        xs: usize,
        n: usize,
        p: &Packed,
        init: &[f32],
        init_stride: usize,
        out: &mut [f32],
    ) {
        gemm(self.isa, x, xs, n, p, init, init_stride, out)
    }

    fn activate(&self, v: &mut [f32]) {
        match self.activation {
            // `x < 0 ? 0 : x` rather than max: a NaN input stays NaN.
            Activation::Relu => v.iter_mut().for_each(|x| *x = relu(*x)),
            Activation::Gelu => v.iter_mut().for_each(|x| *x = gelu(*x)),
        }
    }

    /// One encoder layer on `rows` rows of `x` (stride `xs`): `[LN] -> [act]` after the linear;
    /// returns `rows x pad8(ew)`. Padding columns stay zero (zero weights and bias, LN over the
    /// first `ew` only, act(0) = 0).
    fn enc_layer(&self, l: &EncLayer, x: &[f32], xs: usize, rows: usize) -> Vec<f32> {
        let ewp = pad8(self.ew);
        let mut h = vec![0f32; rows * ewp];
        self.gemm(x, xs, rows, &l.fwd, &l.bias, 0, &mut h);
        if let Some(n) = &l.ln {
            ln_inplace(self.isa, &mut h, &n.g, &n.b, self.eps, rows, ewp, false);
        }
        if l.act {
            self.activate(&mut h);
        }
        h
    }

    /// The observation side for B groups: `trunk.0`'s bias plus its `[ho, e, extras]` columns,
    /// `B x pad8(trunk_dims[0])`.
    fn context(&self, obs: &[f32], extras: &[&[f32]], t: &[u32]) -> Vec<f32> {
        let b = t.len();
        let (od, ew, td, cw) = (self.od, self.ew, self.td, self.cw);
        let mut on = vec![0f32; b * od];
        for (dst, src) in on.chunks_exact_mut(od).zip(obs.chunks_exact(od)) {
            for j in 0..od {
                dst[j] = (src[j] - self.obs_mean[j]) * self.obs_inv_std[j];
            }
        }
        if let Some(n) = &self.obs_in_ln {
            ln_inplace(self.isa, &mut on, &n.g, &n.b, self.eps, b, od, false);
        }
        let ewp = pad8(ew);
        let h = self.enc_layer(&self.obs_enc[0], &on, od, b);
        let ho = self.enc_layer(&self.obs_enc[1], &h, ewp, b);
        let mut xc = vec![0f32; b * cw];
        for r in 0..b {
            let row = &mut xc[r * cw..(r + 1) * cw];
            row[..ew].copy_from_slice(&ho[r * ewp..r * ewp + ew]);
            time_embedding_into(t[r] as f64, &mut row[ew..ew + td]);
        }
        let mut col = ew + td;
        for (e, x) in self.extras.iter().zip(extras) {
            let wp = pad8(e.width);
            let mut h = vec![0f32; b * wp];
            self.gemm(x, e.dim, b, &e.fwd, &e.bias, 0, &mut h);
            for r in 0..b {
                for j in 0..e.width {
                    xc[r * cw + col + j] = relu(h[r * wp + j]);
                }
            }
            col += e.width;
        }
        let t0p = pad8(self.trunk[0].d);
        let mut c0 = vec![0f32; b * t0p];
        self.gemm(&xc, cw, b, &self.trunk0_ctx, &self.trunk[0].bias, 0, &mut c0);
        c0
    }

    /// The chunks as the action encoder takes them (standardised when the artifact says so).
    fn act_input<'a>(&self, chunks: &'a [f32]) -> std::borrow::Cow<'a, [f32]> {
        match &self.act_norm {
            None => std::borrow::Cow::Borrowed(chunks),
            Some((mean, inv_std)) => {
                let mut v = chunks.to_vec();
                for row in v.chunks_exact_mut(self.ad) {
                    for j in 0..self.ad {
                        row[j] = (row[j] - mean[j]) * inv_std[j];
                    }
                }
                std::borrow::Cow::Owned(v)
            }
        }
    }

    /// Head outputs y (logit or value) for B groups of n candidates, into `out` (`B * n`).
    fn forward_y(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], cands: &[f32], n: usize, out: &mut [f32]) {
        let b = t.len();
        let m = b * n;
        let c0 = self.context(obs, extras, t);
        let ewp = pad8(self.ew);
        let a = self.act_input(cands);
        let h1 = self.enc_layer(&self.act_enc[0], &a, self.ad, m);
        let ha = self.enc_layer(&self.act_enc[1], &h1, ewp, m);
        let t0p = pad8(self.trunk[0].d);
        let mut u = vec![0f32; m * t0p];
        for g in 0..b {
            self.gemm(&ha[g * n * ewp..], ewp, n, &self.trunk0_act, &c0[g * t0p..], 0, &mut u[g * n * t0p..]);
        }
        let mut up = t0p;
        for (l, layer) in self.trunk.iter().enumerate() {
            if l > 0 {
                let dp = pad8(layer.d);
                let mut nu = vec![0f32; m * dp];
                self.gemm(&u, up, m, &layer.fwd, &layer.bias, 0, &mut nu);
                u = nu;
                up = dp;
            }
            ln_inplace(self.isa, &mut u, &layer.norm.g, &layer.norm.b, self.eps, m, up, true);
        }
        let d = self.trunk[self.trunk.len() - 1].d;
        for (r, y) in out.iter_mut().enumerate() {
            *y = dot(&u[r * up..r * up + d], &self.head_w) + self.head_b;
        }
    }

    /// Input gradients for B rows into `out` (`B * act_dim`).
    // Past 100 lines on purpose: the hand-derived backward pass, layer by layer in reverse, reads
    // line for line against `forward`; helpers would hide which buffer each step reuses.
    #[allow(clippy::too_many_lines, reason = "the gradient's layers in reverse, read against forward")]
    fn backward(&self, obs: &[f32], extras: &[&[f32]], t: &[u32], chunks: &[f32], out: &mut [f32]) {
        let m = t.len();
        let (ad, ew, eps, isa) = (self.ad, self.ew, self.eps, self.isa);
        let ewp = pad8(ew);
        let c0 = self.context(obs, extras, t);
        let a = self.act_input(chunks);

        // Action encoder forward, keeping what the backward needs.
        struct Saved {
            /// The layer's output: post-activation for ReLU (its mask), pre-activation for GELU
            /// (its derivative), post-LN without activation.
            kept: Vec<f32>,
            xhat: Vec<f32>,
            rstd: Vec<f32>,
        }
        let relu = self.activation == Activation::Relu;
        let mut saved: Vec<Saved> = Vec::with_capacity(2);
        let mut x: std::borrow::Cow<[f32]> = a;
        let mut xs = ad;
        for l in &self.act_enc {
            let mut h = vec![0f32; m * ewp];
            self.gemm(&x, xs, m, &l.fwd, &l.bias, 0, &mut h);
            let (mut xhat, mut rstd) = (Vec::new(), Vec::new());
            if let Some(nm) = &l.ln {
                xhat = vec![0f32; m * ewp];
                rstd = vec![0f32; m];
                let mut normed = vec![0f32; m * ewp];
                ln_forward(
                    isa,
                    &mut h,
                    None,
                    &mut xhat,
                    &mut rstd,
                    &mut normed,
                    &nm.g,
                    &nm.b,
                    eps,
                    m,
                    ewp,
                    false,
                );
                h = normed;
            }
            let next = if l.act && relu {
                self.activate(&mut h);
                h.clone()
            } else if l.act {
                let mut post = h.clone();
                self.activate(&mut post);
                post
            } else {
                h.clone()
            };
            saved.push(Saved { kept: h, xhat, rstd });
            x = std::borrow::Cow::Owned(next);
            xs = ewp;
        }
        let ha = x;

        // Trunk forward, keeping xhat, rstd and the post-ReLU output of each layer.
        let nl = self.trunk.len();
        let mut outs: Vec<Vec<f32>> = Vec::with_capacity(nl);
        let mut xhats: Vec<Vec<f32>> = Vec::with_capacity(nl);
        let mut rstds: Vec<Vec<f32>> = Vec::with_capacity(nl);
        for (l, layer) in self.trunk.iter().enumerate() {
            let dp = pad8(layer.d);
            let mut pre = vec![0f32; m * dp];
            if l == 0 {
                self.gemm(&ha, ewp, m, &self.trunk0_act, &c0, pad8(self.trunk[0].d), &mut pre);
            } else {
                let prev = &outs[l - 1];
                self.gemm(prev, pad8(self.trunk[l - 1].d), m, &layer.fwd, &layer.bias, 0, &mut pre);
            }
            let (mut xhat, mut rstd, mut o) = (vec![0f32; m * dp], vec![0f32; m], vec![0f32; m * dp]);
            ln_forward(
                isa,
                &mut pre,
                None,
                &mut xhat,
                &mut rstd,
                &mut o,
                &layer.norm.g,
                &layer.norm.b,
                eps,
                m,
                dp,
                true,
            );
            outs.push(o);
            xhats.push(xhat);
            rstds.push(rstd);
        }

        // Head: d objective / d z = gy * head_w, gy = 1 - sigmoid(y) (log sigmoid) or 1 (q).
        let last = &self.trunk[nl - 1];
        let lp = pad8(last.d);
        let mut d = vec![0f32; m * lp];
        for r in 0..m {
            let z = &outs[nl - 1][r * lp..r * lp + last.d];
            let gy = match self.kind {
                Kind::Classifier => sigmoid(-(dot(z, &self.head_w) + self.head_b)),
                Kind::Q => 1.0,
            };
            for (dj, w) in d[r * lp..r * lp + last.d].iter_mut().zip(&self.head_w) {
                *dj = gy * w;
            }
        }
        // Trunk backward down to d/d ha.
        let mut dha = vec![0f32; m * ewp];
        for l in (0..nl).rev() {
            let layer = &self.trunk[l];
            let dp = pad8(layer.d);
            ln_backward(
                isa,
                &mut d,
                Some(outs[l].as_slice()),
                &xhats[l],
                &rstds[l],
                &layer.norm.g,
                m,
                dp,
                None,
            );
            if l > 0 {
                let p = &layer.bwd;
                let mut nd = vec![0f32; m * p.mp];
                self.gemm(&d, dp, m, p, &self.zeros, 0, &mut nd);
                d = nd;
            } else {
                self.gemm(&d, dp, m, &self.trunk0_act_bwd, &self.zeros, 0, &mut dha);
            }
        }
        // Action encoder backward.
        let mut g = dha;
        for (li, l) in self.act_enc.iter().enumerate().rev() {
            let s = &saved[li];
            if l.act {
                match self.activation {
                    Activation::Relu => {
                        for (gv, out) in g.iter_mut().zip(&s.kept) {
                            if *out <= 0.0 {
                                *gv = 0.0;
                            }
                        }
                    }
                    Activation::Gelu => {
                        for (gv, pre) in g.iter_mut().zip(&s.kept) {
                            *gv *= gelu_grad(*pre);
                        }
                    }
                }
            }
            if let Some(nm) = &l.ln {
                ln_backward(isa, &mut g, None, &s.xhat, &s.rstd, &nm.g, m, ewp, None);
            }
            let p = l.bwd.as_ref().expect("the action encoder packs its backward weights");
            let mut nd = vec![0f32; m * p.mp];
            self.gemm(&g, ewp, m, p, &self.zeros, 0, &mut nd);
            g = nd;
        }
        let adp = pad8(ad);
        for (r, row) in out.chunks_exact_mut(ad).enumerate() {
            let src = &g[r * adp..r * adp + ad];
            match &self.act_norm {
                None => row.copy_from_slice(src),
                Some((_, inv_std)) => {
                    for j in 0..ad {
                        row[j] = src[j] * inv_std[j];
                    }
                }
            }
        }
    }
}
