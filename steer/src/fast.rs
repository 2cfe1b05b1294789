//! Fast path for the `lowdim` variant (ReLU encoders, no extra inputs): a hand-written f32 forward
//! pass and input-gradient. Weights are packed at load time as `[in][out_padded_to_8]` (forward) and
//! `[out][in_padded_to_8]` (backward, only the layers on the action path). The inner kernel is a
//! register-tiled rows x columns FMA loop with AVX2/FMA (selected at runtime) and a portable fallback.
use crate::config::{Activation, Kind, Variant, VerifierConfig};
use crate::error::{Result, SteerError};
use crate::reference::{check_batch, sigmoid};
use crate::weights::{temb, Weights};
use crate::Scorer;

fn pad8(x: usize) -> usize {
    x.div_ceil(8) * 8
}

/// A matrix packed for `out[r][j] = init[j] + sum_i x[r][i] * w[i][j]`: `k` contraction rows, `m`
/// output columns padded to `mp` (a multiple of 8) with zeros.
#[derive(Clone)]
struct Packed {
    k: usize,
    mp: usize,
    w: Vec<f32>,
}

impl Packed {
    /// From a torch `[out, in]` weight, for the forward pass (contract over `in`), keeping only the
    /// input columns `cols` (in this order).
    fn forward(w: &[f32], out: usize, inp: usize, cols: &[usize]) -> Packed {
        let mp = pad8(out);
        let mut v = vec![0f32; cols.len() * mp];
        for (i, &c) in cols.iter().enumerate() {
            for o in 0..out {
                v[i * mp + o] = w[o * inp + c];
            }
        }
        Packed { k: cols.len(), mp, w: v }
    }
    /// From a torch `[out, in]` weight, for the backward pass (contract over `out`), producing the
    /// gradient w.r.t. the input columns `cols`.
    fn backward(w: &[f32], out: usize, inp: usize, cols: &[usize]) -> Packed {
        let mp = pad8(cols.len());
        let mut v = vec![0f32; out * mp];
        for o in 0..out {
            for (j, &c) in cols.iter().enumerate() {
                v[o * mp + j] = w[o * inp + c];
            }
        }
        Packed { k: out, mp, w: v }
    }
}

fn padded(v: &[f32]) -> Vec<f32> {
    let mut p = v.to_vec();
    p.resize(pad8(v.len()), 0.0);
    p
}

struct TrunkLayer {
    d: usize,
    fwd: Packed, // trunk.l (l >= 1); for l = 0 unused (see trunk0_*)
    bwd: Packed, // d(in) from d(out)
    bias: Vec<f32>,
    g: Vec<f32>,
    b: Vec<f32>,
}

/// The fast lowdim verifier.
pub struct FastLowdim {
    kind: Kind,
    od: usize,
    ad: usize,
    ew: usize,
    td: usize,
    eps: f32,
    avx: bool,
    obs_mean: Vec<f32>,
    obs_inv_std: Vec<f32>,
    act_mean: Vec<f32>,
    act_inv_std: Vec<f32>,
    obs0: Packed,
    obs0_b: Vec<f32>,
    obs1: Packed,
    obs1_b: Vec<f32>,
    act0: Packed,
    act0_b: Vec<f32>,
    act1: Packed,
    act1_b: Vec<f32>,
    act0_bwd: Packed,
    act1_bwd: Packed,
    trunk0_ctx: Packed, // columns [ho ; e]
    trunk0_act: Packed, // columns [ha]
    trunk0_act_bwd: Packed,
    trunk: Vec<TrunkLayer>,
    head_w: Vec<f32>,
    head_b: f32,
}

impl FastLowdim {
    /// Whether the fast path supports this configuration.
    pub fn supports(cfg: &VerifierConfig) -> bool {
        cfg.variant() == Variant::Lowdim
            && cfg.activation() == Activation::Relu
            && cfg.architecture.extra_inputs.is_empty()
    }

    pub fn new(cfg: &VerifierConfig, w: &Weights) -> Result<Self> {
        Self::with_simd(cfg, w, true)
    }

    /// `simd = false` forces the portable kernel (for tests).
    pub fn with_simd(cfg: &VerifierConfig, w: &Weights, simd: bool) -> Result<Self> {
        cfg.validate()?;
        if !Self::supports(cfg) {
            return Err(SteerError::Config(
                "the fast path supports only the lowdim variant with relu and no extra inputs".into(),
            ));
        }
        w.validate(cfg)?;
        let a = &cfg.architecture;
        let (od, ad, ew, td) = (cfg.input.obs_dim, cfg.input.act_dim, a.encoder_width, a.t_embed_dim);
        let t = |n: &str| &w.tensors[n].data;
        let range = |a: usize, b: usize| (a..b).collect::<Vec<_>>();
        let trunk_in = cfg.trunk_in();
        let t0 = a.trunk_dims[0];
        let mut ctx_cols = range(0, ew);
        ctx_cols.extend(2 * ew..2 * ew + td);
        let mut trunk = Vec::new();
        let mut prev = trunk_in;
        for (l, &d) in a.trunk_dims.iter().enumerate() {
            let wl = t(&format!("trunk.{l}.weight"));
            let (fwd, bwd) = if l == 0 {
                (Packed { k: 0, mp: 0, w: vec![] }, Packed { k: 0, mp: 0, w: vec![] })
            } else {
                (Packed::forward(wl, d, prev, &range(0, prev)), Packed::backward(wl, d, prev, &range(0, prev)))
            };
            trunk.push(TrunkLayer {
                d,
                fwd,
                bwd,
                bias: padded(t(&format!("trunk.{l}.bias"))),
                g: t(&format!("trunk.{l}.ln.weight")).clone(),
                b: t(&format!("trunk.{l}.ln.bias")).clone(),
            });
            prev = d;
        }
        let w0 = t("trunk.0.weight");
        let avx = simd && detect_avx2_fma();
        Ok(FastLowdim {
            kind: cfg.kind(),
            od,
            ad,
            ew,
            td,
            eps: a.layernorm_eps as f32,
            avx,
            obs_mean: cfg.input.obs_mean.clone(),
            obs_inv_std: cfg.input.obs_std.iter().map(|s| 1.0 / s).collect(),
            act_mean: cfg.input.act_mean.clone(),
            act_inv_std: cfg.input.act_std.iter().map(|s| 1.0 / s).collect(),
            obs0: Packed::forward(t("obs_enc.0.weight"), ew, od, &range(0, od)),
            obs0_b: padded(t("obs_enc.0.bias")),
            obs1: Packed::forward(t("obs_enc.1.weight"), ew, ew, &range(0, ew)),
            obs1_b: padded(t("obs_enc.1.bias")),
            act0: Packed::forward(t("act_enc.0.weight"), ew, ad, &range(0, ad)),
            act0_b: padded(t("act_enc.0.bias")),
            act1: Packed::forward(t("act_enc.1.weight"), ew, ew, &range(0, ew)),
            act1_b: padded(t("act_enc.1.bias")),
            act0_bwd: Packed::backward(t("act_enc.0.weight"), ew, ad, &range(0, ad)),
            act1_bwd: Packed::backward(t("act_enc.1.weight"), ew, ew, &range(0, ew)),
            trunk0_ctx: Packed::forward(w0, t0, trunk_in, &ctx_cols),
            trunk0_act: Packed::forward(w0, t0, trunk_in, &range(ew, 2 * ew)),
            trunk0_act_bwd: Packed::backward(w0, t0, trunk_in, &range(ew, 2 * ew)),
            trunk,
            head_w: t("head.weight").clone(),
            head_b: t("head.bias")[0],
        })
    }

    /// True when the AVX2/FMA kernel is in use.
    pub fn uses_simd(&self) -> bool {
        self.avx
    }

    /// `out (n x p.mp) = init (broadcast if init_stride == 0) + x (n rows, stride xs) @ p`.
    fn gemm(&self, x: &[f32], xs: usize, n: usize, p: &Packed, init: &[f32], init_stride: usize, out: &mut [f32]) {
        debug_assert!(n == 0 || x.len() >= (n - 1) * xs + p.k);
        debug_assert!(out.len() >= n * p.mp);
        debug_assert!(init.len() >= init_stride * n.saturating_sub(1) + p.mp);
        #[cfg(target_arch = "x86_64")]
        if self.avx {
            // SAFETY: the CPU supports avx2+fma (checked at construction); slices are large enough
            // (debug-asserted above, guaranteed by the callers' buffer sizing).
            unsafe { simd::gemm(x.as_ptr(), xs, n, p.k, p.w.as_ptr(), p.mp, init.as_ptr(), init_stride, out.as_mut_ptr()) };
            return;
        }
        gemm_portable(x, xs, n, p, init, init_stride, out)
    }

    /// Context rows for B (obs, t) pairs: c0 = trunk.0 bias + W0[:, ho] ho + W0[:, e] e.
    fn context(&self, obs: &[f32], t: &[u32]) -> Vec<f32> {
        let b = t.len();
        let (od, ew, td) = (self.od, self.ew, self.td);
        let mut on = vec![0f32; b * od];
        for r in 0..b {
            for j in 0..od {
                on[r * od + j] = (obs[r * od + j] - self.obs_mean[j]) * self.obs_inv_std[j];
            }
        }
        let ewp = pad8(ew);
        let mut h1 = vec![0f32; b * ewp];
        self.gemm(&on, od, b, &self.obs0, &self.obs0_b, 0, &mut h1);
        relu(&mut h1);
        // x_ctx = [ho, e] rows of width ew + td
        let cw = ew + td;
        let mut h2 = vec![0f32; b * ewp];
        self.gemm(&h1, ewp, b, &self.obs1, &self.obs1_b, 0, &mut h2);
        let mut xc = vec![0f32; b * cw];
        for r in 0..b {
            for j in 0..ew {
                xc[r * cw + j] = h2[r * ewp + j].max(0.0);
            }
            temb(t[r], td, &mut xc[r * cw + ew..(r + 1) * cw]);
        }
        let t0p = pad8(self.trunk[0].d);
        let mut c0 = vec![0f32; b * t0p];
        self.gemm(&xc, cw, b, &self.trunk0_ctx, &self.trunk[0].bias, 0, &mut c0);
        c0
    }

    fn normalize_act(&self, a: &[f32], out: &mut [f32]) {
        for (r, row) in a.chunks_exact(self.ad).enumerate() {
            let o = &mut out[r * self.ad..(r + 1) * self.ad];
            for j in 0..self.ad {
                o[j] = (row[j] - self.act_mean[j]) * self.act_inv_std[j];
            }
        }
    }

    fn ln_stats(&self, u: &[f32], d: usize) -> (f32, f32) {
        let mean = u[..d].iter().sum::<f32>() / d as f32;
        let var = u[..d].iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / d as f32;
        (mean, 1.0 / (var + self.eps).sqrt())
    }

    /// Raw outputs y for B groups of n candidates.
    pub fn forward_y(&self, obs: &[f32], t: &[u32], cands: &[f32], n: usize) -> Vec<f32> {
        let b = t.len();
        let m = b * n;
        let c0 = self.context(obs, t);
        let ewp = pad8(self.ew);
        let mut an = vec![0f32; m * self.ad];
        self.normalize_act(cands, &mut an);
        let mut h1 = vec![0f32; m * ewp];
        self.gemm(&an, self.ad, m, &self.act0, &self.act0_b, 0, &mut h1);
        relu(&mut h1);
        let mut h2 = vec![0f32; m * ewp];
        self.gemm(&h1, ewp, m, &self.act1, &self.act1_b, 0, &mut h2);
        relu(&mut h2);
        let t0p = pad8(self.trunk[0].d);
        let mut u = vec![0f32; m * t0p];
        for g in 0..b {
            self.gemm(&h2[g * n * ewp..], ewp, n, &self.trunk0_act, &c0[g * t0p..], 0, &mut u[g * n * t0p..]);
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
            for r in 0..m {
                let row = &mut u[r * up..r * up + layer.d];
                let (mean, rstd) = self.ln_stats(row, layer.d);
                for j in 0..layer.d {
                    row[j] = ((row[j] - mean) * rstd * layer.g[j] + layer.b[j]).max(0.0);
                }
            }
        }
        let d = self.trunk.last().unwrap().d;
        (0..m).map(|r| dot(&u[r * up..r * up + d], &self.head_w) + self.head_b).collect()
    }

    /// Gradient for one (obs, t, chunk) row.
    fn grad_row(&self, obs: &[f32], t: u32, chunk: &[f32], out: &mut [f32]) {
        let ewp = pad8(self.ew);
        let c0 = self.context(obs, &[t]);
        let mut an = vec![0f32; self.ad];
        self.normalize_act(chunk, &mut an);
        let mut v1 = vec![0f32; ewp];
        self.gemm(&an, self.ad, 1, &self.act0, &self.act0_b, 0, &mut v1);
        let mut r1 = v1.clone();
        relu(&mut r1);
        let mut v2 = vec![0f32; ewp];
        self.gemm(&r1, ewp, 1, &self.act1, &self.act1_b, 0, &mut v2);
        let mut ha = v2.clone();
        relu(&mut ha);
        // trunk forward, keeping xhat, rstd and the post-LN pre-relu value s
        let nl = self.trunk.len();
        let mut xhats: Vec<Vec<f32>> = Vec::with_capacity(nl);
        let mut ss: Vec<Vec<f32>> = Vec::with_capacity(nl);
        let mut rstds = Vec::with_capacity(nl);
        let mut h: Vec<f32> = Vec::new();
        for (l, layer) in self.trunk.iter().enumerate() {
            let dp = pad8(layer.d);
            let mut u = vec![0f32; dp];
            if l == 0 {
                self.gemm(&ha, ewp, 1, &self.trunk0_act, &c0, 0, &mut u);
            } else {
                self.gemm(&h, h.len(), 1, &layer.fwd, &layer.bias, 0, &mut u);
            }
            let (mean, rstd) = self.ln_stats(&u, layer.d);
            let mut xh = vec![0f32; layer.d];
            let mut s = vec![0f32; layer.d];
            let mut hn = vec![0f32; dp];
            for j in 0..layer.d {
                xh[j] = (u[j] - mean) * rstd;
                s[j] = xh[j] * layer.g[j] + layer.b[j];
                hn[j] = s[j].max(0.0);
            }
            xhats.push(xh);
            ss.push(s);
            rstds.push(rstd);
            h = hn;
        }
        let d = self.trunk[nl - 1].d;
        let y = dot(&h[..d], &self.head_w) + self.head_b;
        let gy = match self.kind {
            Kind::Classifier => sigmoid(-y), // d log sigmoid(y) / dy = 1 - sigmoid(y)
            Kind::Q => 1.0,
        };
        let mut dh: Vec<f32> = self.head_w.iter().map(|w| gy * w).collect();
        let mut dha = vec![0f32; ewp];
        for l in (0..nl).rev() {
            let layer = &self.trunk[l];
            let dd = layer.d;
            let (xh, s) = (&xhats[l], &ss[l]);
            let mut dxh = vec![0f32; dd];
            for j in 0..dd {
                dxh[j] = if s[j] > 0.0 { dh[j] * layer.g[j] } else { 0.0 };
            }
            let m1 = dxh.iter().sum::<f32>() / dd as f32;
            let m2 = dxh.iter().zip(xh).map(|(a, b)| a * b).sum::<f32>() / dd as f32;
            let du: Vec<f32> = (0..dd).map(|j| rstds[l] * (dxh[j] - m1 - xh[j] * m2)).collect();
            if l > 0 {
                let p = &layer.bwd;
                let mut nd = vec![0f32; p.mp];
                self.gemm(&du, dd, 1, p, &vec![0f32; p.mp], 0, &mut nd);
                dh = nd;
            } else {
                let zero = vec![0f32; ewp];
                self.gemm(&du, dd, 1, &self.trunk0_act_bwd, &zero, 0, &mut dha);
            }
        }
        for j in 0..self.ew {
            if v2[j] <= 0.0 {
                dha[j] = 0.0;
            }
        }
        let zero = vec![0f32; pad8(self.ad.max(self.ew))];
        let mut dr1 = vec![0f32; ewp];
        self.gemm(&dha, ewp, 1, &self.act1_bwd, &zero, 0, &mut dr1);
        for j in 0..self.ew {
            if v1[j] <= 0.0 {
                dr1[j] = 0.0;
            }
        }
        let mut da = vec![0f32; pad8(self.ad)];
        self.gemm(&dr1, ewp, 1, &self.act0_bwd, &zero, 0, &mut da);
        for j in 0..self.ad {
            out[j] = da[j] * self.act_inv_std[j];
        }
    }
}

fn relu(v: &mut [f32]) {
    for x in v {
        *x = x.max(0.0);
    }
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut s = [0f32; 8];
    let n8 = a.len() / 8 * 8;
    for i in (0..n8).step_by(8) {
        for l in 0..8 {
            s[l] += a[i + l] * b[i + l];
        }
    }
    let mut t = s.iter().sum::<f32>();
    for i in n8..a.len() {
        t += a[i] * b[i];
    }
    t
}

fn gemm_portable(x: &[f32], xs: usize, n: usize, p: &Packed, init: &[f32], is: usize, out: &mut [f32]) {
    let mp = p.mp;
    for r in 0..n {
        let o = &mut out[r * mp..(r + 1) * mp];
        o.copy_from_slice(&init[r * is..r * is + mp]);
        for i in 0..p.k {
            let xv = x[r * xs + i];
            if xv == 0.0 {
                continue;
            }
            let w = &p.w[i * mp..(i + 1) * mp];
            for j in 0..mp {
                o[j] += xv * w[j];
            }
        }
    }
}

fn detect_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(target_arch = "x86_64")]
mod simd {
    use std::arch::x86_64::*;

    /// R rows x (8*B) columns tile starting at column c.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn tile<const R: usize, const B: usize>(
        x: *const f32, xs: usize, k: usize, w: *const f32, mp: usize, init: *const f32, is: usize,
        out: *mut f32, c: usize,
    ) {
        let mut acc = [[_mm256_setzero_ps(); B]; R];
        for r in 0..R {
            for b in 0..B {
                acc[r][b] = _mm256_loadu_ps(init.add(r * is + c + 8 * b));
            }
        }
        let mut wp = w.add(c);
        for i in 0..k {
            let mut wv = [_mm256_setzero_ps(); B];
            for b in 0..B {
                wv[b] = _mm256_loadu_ps(wp.add(8 * b));
            }
            for r in 0..R {
                let xv = _mm256_set1_ps(*x.add(r * xs + i));
                for b in 0..B {
                    acc[r][b] = _mm256_fmadd_ps(xv, wv[b], acc[r][b]);
                }
            }
            wp = wp.add(mp);
        }
        for r in 0..R {
            for b in 0..B {
                _mm256_storeu_ps(out.add(r * mp + c + 8 * b), acc[r][b]);
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn rows<const R: usize, const B: usize>(
        x: *const f32, xs: usize, k: usize, w: *const f32, mp: usize, init: *const f32, is: usize,
        out: *mut f32,
    ) {
        let mut c = 0;
        while c + 8 * B <= mp {
            tile::<R, B>(x, xs, k, w, mp, init, is, out, c);
            c += 8 * B;
        }
        while c < mp {
            tile::<R, 1>(x, xs, k, w, mp, init, is, out, c);
            c += 8;
        }
    }

    /// See `FastLowdim::gemm`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn gemm(
        x: *const f32, xs: usize, n: usize, k: usize, w: *const f32, mp: usize, init: *const f32,
        is: usize, out: *mut f32,
    ) {
        let mut r = 0;
        while r + 4 <= n {
            rows::<4, 2>(x.add(r * xs), xs, k, w, mp, init.add(r * is), is, out.add(r * mp));
            r += 4;
        }
        while r + 2 <= n {
            rows::<2, 4>(x.add(r * xs), xs, k, w, mp, init.add(r * is), is, out.add(r * mp));
            r += 2;
        }
        while r < n {
            rows::<1, 4>(x.add(r * xs), xs, k, w, mp, init.add(r * is), is, out.add(r * mp));
            r += 1;
        }
    }
}

impl Scorer for FastLowdim {
    fn obs_dim(&self) -> usize {
        self.od
    }
    fn act_dim(&self) -> usize {
        self.ad
    }
    fn score_batch(&self, obs: &[f32], t: &[u32], candidates: &[f32], n: usize) -> Result<Vec<f32>> {
        check_batch(self.od, self.ad, obs, t, candidates, n)?;
        let y = self.forward_y(obs, t, candidates, n);
        Ok(match self.kind {
            Kind::Classifier => y.into_iter().map(sigmoid).collect(),
            Kind::Q => y,
        })
    }
    fn grad_batch(&self, obs: &[f32], t: &[u32], chunks: &[f32]) -> Result<Vec<f32>> {
        check_batch(self.od, self.ad, obs, t, chunks, 1)?;
        let mut out = vec![0f32; chunks.len()];
        for r in 0..t.len() {
            self.grad_row(
                &obs[r * self.od..(r + 1) * self.od],
                t[r],
                &chunks[r * self.ad..(r + 1) * self.ad],
                &mut out[r * self.ad..(r + 1) * self.ad],
            );
        }
        Ok(out)
    }
}
