//! Fused fast path for training the `lowdim` architecture without extra inputs: a hand-written
//! f32 forward/backward over preallocated buffers (matrix products through the `gemm` crate that
//! candle itself uses, elementwise work fused per layer, AVX2/FMA kernels selected at runtime).
//! The LayerNorm kernels are the verifier core's (`verifier::kernels`), shared with inference;
//! the ones here (bias + ReLU, the head) are training-only.
//!
//! It computes exactly the model of `model.rs` (tested against the candle graph: values and
//! gradients), observation noise included, reading and writing the same [`ParamSet`] layout.
//!
//! One file past 700 lines: the fused forward and backward passes and their buffers are read
//! against each other.
#![allow(unsafe_code, reason = "the fused AVX2 training kernels: target-feature calls")]

use anyhow::{ensure, Result};

use crate::loss::{objective_host, LossConfig};
use crate::model::{Kind, ModelSpec, ParamSet, Variant};
use verifier::kernels::{ln_backward, ln_forward, Isa, LnGrads};

/// Whether the fused path supports this model.
pub fn supports(spec: &ModelSpec) -> bool {
    let a = &spec.arch;
    a.variant == Variant::Lowdim
        && !a.input_layernorm
        && !a.encoder_layernorm
        && !a.spectral_norm
        && a.extra_inputs.is_empty()
        && a.activation == crate::model::Activation::Relu
}

#[derive(Clone, Copy)]
struct Lin {
    w: usize,
    b: usize,
    input: usize,
    output: usize,
}

#[derive(Clone, Copy)]
struct TrunkLayer {
    lin: Lin,
    g: usize,
    beta: usize,
}

/// C = A * B (+ C when `acc`), general strides (row stride `rs`, column stride `cs`).
#[allow(clippy::too_many_arguments)]
#[inline]
unsafe fn mm(
    m: usize,
    n: usize,
    k: usize,
    dst: *mut f32,
    dst_rs: usize,
    dst_cs: usize,
    acc: bool,
    lhs: *const f32,
    lhs_rs: usize,
    lhs_cs: usize,
    rhs: *const f32,
    rhs_rs: usize,
    rhs_cs: usize,
) {
    gemm::gemm(
        m,
        n,
        k,
        dst,
        dst_cs as isize,
        dst_rs as isize,
        acc,
        lhs,
        lhs_cs as isize,
        lhs_rs as isize,
        rhs,
        rhs_cs as isize,
        rhs_rs as isize,
        1.0,
        1.0,
        false,
        false,
        false,
        gemm::Parallelism::None,
    )
}

macro_rules! kernels {
    ($modname:ident, $($feat:literal),*) => {
        mod $modname {
            //! Elementwise kernels (compiled once per instruction set).
            $(#[target_feature(enable = $feat)])*
            /// `x = max(x + b, 0)` on `rows` rows of width `b.len()` with row stride `rs`.
            pub unsafe fn bias_relu(x: &mut [f32], rows: usize, rs: usize, b: &[f32]) {
                let n = b.len();
                for r in 0..rows {
                    let row = &mut x[r * rs..r * rs + n];
                    for (v, bb) in row.iter_mut().zip(b) {
                        *v = (*v + bb).max(0.0);
                    }
                }
            }

            $(#[target_feature(enable = $feat)])*
            /// Backward of `relu`: zero `d` where `out <= 0`, accumulate column sums into `db`.
            pub unsafe fn relu_back_colsum(
                d: &mut [f32], d_rs: usize, out: &[f32], out_rs: usize, rows: usize, db: &mut [f32],
            ) {
                let n = db.len();
                for r in 0..rows {
                    let dr = &mut d[r * d_rs..r * d_rs + n];
                    let or = &out[r * out_rs..r * out_rs + n];
                    for ((dv, ov), s) in dr.iter_mut().zip(or).zip(db.iter_mut()) {
                        let v = if *ov > 0.0 { *dv } else { 0.0 };
                        *dv = v;
                        *s += v;
                    }
                }
            }

            $(#[target_feature(enable = $feat)])*
            /// Head forward: `y[r] = sum_k z[r,k] * mask[r,k] * w[k] + b`.
            pub unsafe fn head_fwd(z: &[f32], mask: Option<&[f32]>, w: &[f32], b: f32, y: &mut [f32]) {
                let n = w.len();
                let n8 = n - n % 8;
                for (r, yr) in y.iter_mut().enumerate() {
                    let zr = &z[r * n..(r + 1) * n];
                    let mut acc = [0.0f32; 8];
                    let mut s = 0.0f32;
                    match mask {
                        Some(m) => {
                            let mr = &m[r * n..(r + 1) * n];
                            let mut k = 0;
                            while k < n8 {
                                for l in 0..8 {
                                    acc[l] += zr[k + l] * mr[k + l] * w[k + l];
                                }
                                k += 8;
                            }
                            for k in n8..n {
                                s += zr[k] * mr[k] * w[k];
                            }
                        }
                        None => {
                            let mut k = 0;
                            while k < n8 {
                                for l in 0..8 {
                                    acc[l] += zr[k + l] * w[k + l];
                                }
                                k += 8;
                            }
                            for k in n8..n {
                                s += zr[k] * w[k];
                            }
                        }
                    }
                    *yr = s + super::hsum(acc) + b;
                }
            }

            $(#[target_feature(enable = $feat)])*
            /// Head backward: `dz += dy * mask * w`, `dw += dy * z * mask`, returns `sum dy`.
            pub unsafe fn head_back(
                z: &[f32], mask: Option<&[f32]>, w: &[f32], dy: &[f32], dz: &mut [f32], dw: &mut [f32],
            ) -> f32 {
                let n = w.len();
                let mut sb = 0.0f32;
                for (r, &g) in dy.iter().enumerate() {
                    sb += g;
                    let zr = &z[r * n..(r + 1) * n];
                    let dzr = &mut dz[r * n..(r + 1) * n];
                    match mask {
                        Some(m) => {
                            let mr = &m[r * n..(r + 1) * n];
                            for k in 0..n {
                                let gm = g * mr[k];
                                dzr[k] += gm * w[k];
                                dw[k] += gm * zr[k];
                            }
                        }
                        None => {
                            for k in 0..n {
                                dzr[k] += g * w[k];
                                dw[k] += g * zr[k];
                            }
                        }
                    }
                }
                sb
            }
        }
    };
}

#[inline(always)]
fn hsum(a: [f32; 8]) -> f32 {
    ((a[0] + a[4]) + (a[1] + a[5])) + ((a[2] + a[6]) + (a[3] + a[7]))
}

kernels!(k_avx2, "avx2", "fma");

kernels!(k_base,);

/// Runs an elementwise kernel compiled for the selected instruction set.
macro_rules! dispatch {
    ($isa:expr, $f:ident ( $($arg:expr),* )) => {
        match $isa {
            #[allow(unused_unsafe)]
            // SAFETY: `Isa::Avx2Fma` is only ever detected on a CPU with AVX2 and FMA; the
            // kernels take slices, no raw pointers.
            Isa::Avx2Fma => unsafe { k_avx2::$f($($arg),*) },
            #[allow(unused_unsafe)]
            // SAFETY: the portable build of the same kernels needs no CPU feature.
            Isa::Portable => unsafe { k_base::$f($($arg),*) },
        }
    };
}

/// Buffers and forward/backward for one (sub-)batch of at most `cap` rows.
struct Worker {
    cap: usize,
    rows: usize,
    obs: Vec<f32>,
    act: Vec<f32>,
    h_o: Vec<f32>,
    h_a: Vec<f32>,
    /// Trunk input `[rows, trunk_in]` = concat(ho, ha, temb).
    x: Vec<f32>,
    pre: Vec<Vec<f32>>,
    xhat: Vec<Vec<f32>>,
    rstd: Vec<Vec<f32>>,
    out: Vec<Vec<f32>>,
    y: Vec<f32>,
    dz: Vec<f32>,
    /// Scratch for d/d(trunk layer input), sized for the widest trunk input.
    dtmp: Vec<f32>,
    dh: Vec<f32>,
    grads: Vec<Vec<f32>>,
}

/// The fused fast path: forward, loss and backward for the lowdim verifier.
pub struct FastModel {
    spec: ModelSpec,
    isa: Isa,
    o0: Lin,
    o1: Lin,
    a0: Lin,
    a1: Lin,
    trunk: Vec<TrunkLayer>,
    head: Lin,
    trunk_in: usize,
    eps: f32,
    workers: Vec<Worker>,
    /// Gradients summed over workers, in `ParamSet` order.
    pub grads: Vec<Vec<f32>>,
    y: Vec<f32>,
    z: Vec<f32>,
    dy: Vec<f32>,
    dz: Vec<f32>,
}

/// A batch as row indices into standardised sample arrays.
pub struct BatchSource<'a> {
    /// `[n, obs_dim]` standardised.
    pub obs: &'a [f32],
    /// `[n, act_dim]` standardised.
    pub act: &'a [f32],
    pub t: &'a [u32],
    /// Step-embedding table (`ensure`d up to the max step).
    pub temb: &'a crate::data::TimeEmbedTable,
}

impl FastModel {
    /// `threads` workers split each batch of at most `batch` rows (data parallel).
    pub fn new(spec: &ModelSpec, params: &ParamSet, batch: usize, threads: usize) -> Result<Self> {
        ensure!(supports(spec), "fast path supports lowdim without extras only");
        spec.check_params(params)?;
        let idx = |n: &str| params.index(n).expect("check_params: every tensor the spec names is present");
        let lin = |name: &str| {
            let w = idx(&format!("{name}.weight"));
            Lin {
                w,
                b: idx(&format!("{name}.bias")),
                input: params.shapes[w][1],
                output: params.shapes[w][0],
            }
        };
        let trunk: Vec<TrunkLayer> = (0..spec.arch.trunk_dims.len())
            .map(|i| TrunkLayer {
                lin: lin(&format!("trunk.{i}")),
                g: idx(&format!("trunk.{i}.ln.weight")),
                beta: idx(&format!("trunk.{i}.ln.bias")),
            })
            .collect();
        let threads = threads.clamp(1, 16);
        let cap = batch.div_ceil(threads);
        let trunk_in = spec.arch.trunk_in();
        let w = spec.arch.encoder_width;
        let zdim = spec.arch.z_dim();
        let widest = trunk.iter().map(|l| l.lin.input).max().unwrap_or(0);
        let workers = (0..threads)
            .map(|_| Worker {
                cap,
                rows: 0,
                obs: vec![0.0; cap * spec.obs_dim],
                act: vec![0.0; cap * spec.act_dim],
                h_o: vec![0.0; cap * w],
                h_a: vec![0.0; cap * w],
                x: vec![0.0; cap * trunk_in],
                pre: trunk.iter().map(|l| vec![0.0; cap * l.lin.output]).collect(),
                xhat: trunk.iter().map(|l| vec![0.0; cap * l.lin.output]).collect(),
                rstd: trunk.iter().map(|_| vec![0.0; cap]).collect(),
                out: trunk.iter().map(|l| vec![0.0; cap * l.lin.output]).collect(),
                y: vec![0.0; cap],
                dz: vec![0.0; cap * zdim],
                dtmp: vec![0.0; cap * widest],
                dh: vec![0.0; cap * w],
                grads: params.zeros_like(),
            })
            .collect();
        Ok(FastModel {
            spec: spec.clone(),
            isa: Isa::detect(),
            o0: lin("obs_enc.0"),
            o1: lin("obs_enc.1"),
            a0: lin("act_enc.0"),
            a1: lin("act_enc.1"),
            trunk,
            head: lin("head"),
            trunk_in,
            eps: spec.arch.layernorm_eps as f32,
            workers,
            grads: params.zeros_like(),
            y: vec![0.0; batch],
            z: vec![0.0; batch * zdim],
            dy: vec![0.0; batch],
            dz: vec![0.0; batch * zdim],
        })
    }

    /// Use the portable (non-AVX2) kernels (for testing both paths).
    pub fn force_portable(&mut self) {
        self.isa = Isa::Portable;
    }

    fn zdim(&self) -> usize {
        self.spec.arch.z_dim()
    }

    /// Head outputs of the last forward pass.
    pub fn y(&self) -> &[f32] {
        &self.y
    }
    /// Penultimate features of the last forward pass.
    pub fn z(&self) -> &[f32] {
        &self.z
    }

    #[allow(clippy::type_complexity)]
    /// Forward pass over `rows` (indices into `src`); `mask` is the scaled dropout mask
    /// `[rows.len(), zdim]` and `obs_noise` the Gaussian noise `[rows.len(), obs_dim]` added to
    /// the standardised observation (both None at evaluation). Results in [`Self::y`] / [`Self::z`].
    pub fn forward(
        &mut self,
        p: &ParamSet,
        src: &BatchSource,
        rows: &[u32],
        mask: Option<&[f32]>,
        obs_noise: Option<&[f32]>,
    ) {
        let n = rows.len();
        let zdim = self.zdim();
        self.y.resize(n.max(self.y.len()), 0.0);
        self.z.resize((n * zdim).max(self.z.len()), 0.0);
        let nw = self.workers.len();
        let cap = self.workers[0].cap;
        assert!(n <= cap * nw, "batch larger than the fast path's capacity");
        let od = self.spec.obs_dim;
        if let Some(noise) = obs_noise {
            assert_eq!(noise.len(), n * od, "observation noise: one value per batch row and obs dim");
        }
        let chunk = n.div_ceil(nw).max(1);
        let mut workers = std::mem::take(&mut self.workers);
        {
            let ctx = Ctx { m: &*self, p };
            let jobs: Vec<(&mut Worker, &[u32], Option<&[f32]>, Option<&[f32]>)> = workers
                .iter_mut()
                .enumerate()
                .map(|(i, w)| {
                    let s = (i * chunk).min(n);
                    let e = ((i + 1) * chunk).min(n);
                    (
                        w,
                        &rows[s..e],
                        mask.map(|m| &m[s * zdim..e * zdim]),
                        obs_noise.map(|x| &x[s * od..e * od]),
                    )
                })
                .collect();
            run_parallel(jobs, |(w, r, m, x)| ctx.forward(w, src, r, m, x));
        }
        let mut off = 0;
        for w in &workers {
            self.y[off..off + w.rows].copy_from_slice(&w.y[..w.rows]);
            let zl = w.out.last().expect("a worker holds one output per trunk layer");
            self.z[off * zdim..(off + w.rows) * zdim].copy_from_slice(&zl[..w.rows * zdim]);
            off += w.rows;
        }
        self.workers = workers;
    }

    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    /// One training step's forward, loss and backward: returns the loss; gradients in
    /// [`Self::grads`] (overwritten).
    pub fn loss_and_grads(
        &mut self,
        p: &ParamSet,
        src: &BatchSource,
        rows: &[u32],
        target: &[f32],
        mask: Option<&[f32]>,
        obs_noise: Option<&[f32]>,
        kind: Kind,
        loss_cfg: &LossConfig,
    ) -> f64 {
        self.forward(p, src, rows, mask, obs_noise);
        let n = rows.len();
        let zdim = self.zdim();
        self.dy.resize(n.max(self.dy.len()), 0.0);
        self.dz.resize((n * zdim).max(self.dz.len()), 0.0);
        let loss = objective_host(
            kind,
            &self.y[..n],
            &self.z[..n * zdim],
            zdim,
            target,
            loss_cfg,
            Some((&mut self.dy[..n], &mut self.dz[..n * zdim])),
        );
        let mut workers = std::mem::take(&mut self.workers);
        {
            let ctx = Ctx { m: &*self, p };
            let mut off = 0;
            let jobs: Vec<(&mut Worker, &[f32], &[f32], Option<&[f32]>)> = workers
                .iter_mut()
                .map(|w| {
                    let r = w.rows;
                    let j = (
                        w,
                        &self.dy[off..off + r],
                        &self.dz[off * zdim..(off + r) * zdim],
                        mask.map(|m| &m[off * zdim..(off + r) * zdim]),
                    );
                    off += r;
                    j
                })
                .collect();
            run_parallel(jobs, |(w, dy, dz, m)| ctx.backward(w, dy, dz, m));
        }
        for (gi, g) in self.grads.iter_mut().enumerate() {
            g.copy_from_slice(&workers[0].grads[gi]);
            for w in &workers[1..] {
                for (a, b) in g.iter_mut().zip(&w.grads[gi]) {
                    *a += b;
                }
            }
        }
        self.workers = workers;
        loss
    }
}

fn run_parallel<J: Send, F: Fn(J) + Sync>(jobs: Vec<J>, f: F) {
    if jobs.len() == 1 {
        jobs.into_iter().for_each(f);
        return;
    }
    std::thread::scope(|s| {
        let mut it = jobs.into_iter();
        let first = it.next();
        let f = &f;
        let handles: Vec<_> = it.map(|j| s.spawn(move || f(j))).collect();
        if let Some(j) = first {
            f(j);
        }
        for h in handles {
            h.join().expect("fast path worker panicked");
        }
    });
}

struct Ctx<'a> {
    m: &'a FastModel,
    p: &'a ParamSet,
}

impl Ctx<'_> {
    // Past 100 lines on purpose: the network's forward pass in one place, each layer's kernel
    // dispatched in turn, so `backward` can be read against it.
    #[allow(
        clippy::too_many_lines,
        reason = "a fused pass: each layer's kernel calls in order, read against the candle graph"
    )]
    fn forward(
        &self,
        w: &mut Worker,
        src: &BatchSource,
        rows: &[u32],
        mask: Option<&[f32]>,
        obs_noise: Option<&[f32]>,
    ) {
        let m = self.m;
        let p = &self.p.values;
        let n = rows.len();
        w.rows = n;
        if n == 0 {
            return;
        }
        let (od, ad) = (m.spec.obs_dim, m.spec.act_dim);
        let ew = m.spec.arch.encoder_width;
        let te = m.spec.arch.t_embed_dim;
        let ti = m.trunk_in;
        // Gather.
        for (r, &i) in rows.iter().enumerate() {
            let i = i as usize;
            w.obs[r * od..(r + 1) * od].copy_from_slice(&src.obs[i * od..(i + 1) * od]);
            w.act[r * ad..(r + 1) * ad].copy_from_slice(&src.act[i * ad..(i + 1) * ad]);
            w.x[r * ti + 2 * ew..r * ti + 2 * ew + te].copy_from_slice(src.temb.get(src.t[i]));
        }
        // Noise on the standardised observation (the lowdim model has no input LayerNorm); the
        // noisy input is also what obs_enc.0's weight gradient sees, as in the candle graph.
        if let Some(noise) = obs_noise {
            for (o, e) in w.obs[..n * od].iter_mut().zip(noise) {
                *o += e;
            }
        }
        // SAFETY: the kernel calls below run the instruction set `m.isa` was detected for, on
        // slices (no raw pointers).
        unsafe {
            // Encoders.
            let l = m.o0;
            mm(
                n,
                l.output,
                l.input,
                w.h_o.as_mut_ptr(),
                ew,
                1,
                false,
                w.obs.as_ptr(),
                od,
                1,
                p[l.w].as_ptr(),
                1,
                l.input,
            );
            dispatch!(m.isa, bias_relu(&mut w.h_o, n, ew, &p[l.b]));
            let l = m.o1;
            mm(
                n,
                l.output,
                l.input,
                w.x.as_mut_ptr(),
                ti,
                1,
                false,
                w.h_o.as_ptr(),
                ew,
                1,
                p[l.w].as_ptr(),
                1,
                l.input,
            );
            dispatch!(m.isa, bias_relu(&mut w.x, n, ti, &p[l.b]));
            let l = m.a0;
            mm(
                n,
                l.output,
                l.input,
                w.h_a.as_mut_ptr(),
                ew,
                1,
                false,
                w.act.as_ptr(),
                ad,
                1,
                p[l.w].as_ptr(),
                1,
                l.input,
            );
            dispatch!(m.isa, bias_relu(&mut w.h_a, n, ew, &p[l.b]));
            let l = m.a1;
            mm(
                n,
                l.output,
                l.input,
                w.x.as_mut_ptr().add(ew),
                ti,
                1,
                false,
                w.h_a.as_ptr(),
                ew,
                1,
                p[l.w].as_ptr(),
                1,
                l.input,
            );
            dispatch!(m.isa, bias_relu(&mut w.x[ew..], n, ti, &p[l.b]));
            // Trunk.
            for (i, tl) in m.trunk.iter().enumerate() {
                let l = tl.lin;
                let (inp, ins): (*const f32, usize) =
                    if i == 0 { (w.x.as_ptr(), ti) } else { (w.out[i - 1].as_ptr(), l.input) };
                mm(
                    n,
                    l.output,
                    l.input,
                    w.pre[i].as_mut_ptr(),
                    l.output,
                    1,
                    false,
                    inp,
                    ins,
                    1,
                    p[l.w].as_ptr(),
                    1,
                    l.input,
                );
                ln_forward(
                    m.isa,
                    &mut w.pre[i],
                    Some(p[l.b].as_slice()),
                    &mut w.xhat[i],
                    &mut w.rstd[i],
                    &mut w.out[i],
                    &p[tl.g],
                    &p[tl.beta],
                    m.eps,
                    n,
                    l.output,
                    true,
                );
            }
            let z = w.out.last().expect("a worker holds one output per trunk layer");
            let h = m.head;
            dispatch!(m.isa, head_fwd(&z[..n * h.input], mask, &p[h.w], p[h.b][0], &mut w.y[..n]));
        }
    }

    // Past 100 lines on purpose: the hand-derived backward pass, layer by layer in reverse, reads
    // line for line against `forward`; helpers would hide which buffer each step reuses.
    #[allow(
        clippy::too_many_lines,
        reason = "a fused pass: each layer's kernel calls in reverse, read against forward"
    )]
    fn backward(&self, w: &mut Worker, dy: &[f32], dz: &[f32], mask: Option<&[f32]>) {
        let m = self.m;
        let p = &self.p.values;
        let n = w.rows;
        for g in w.grads.iter_mut() {
            g.iter_mut().for_each(|x| *x = 0.0);
        }
        if n == 0 {
            return;
        }
        let (od, ad) = (m.spec.obs_dim, m.spec.act_dim);
        let ew = m.spec.arch.encoder_width;
        let ti = m.trunk_in;
        let nt = m.trunk.len();
        let h = m.head;
        let zdim = h.input;
        // d/dz = contrastive part + head part.
        w.dz[..n * zdim].copy_from_slice(&dz[..n * zdim]);
        {
            let (gw, gb) = split_two(&mut w.grads, h.w, h.b);
            let z = &w.out[nt - 1];
            let s = dispatch!(
                m.isa,
                head_back(&z[..n * zdim], mask, &p[h.w], &dy[..n], &mut w.dz[..n * zdim], gw)
            );
            gb[0] += s;
        }
        // SAFETY: the kernel calls below run the instruction set `m.isa` was detected for, on
        // slices (no raw pointers).
        unsafe {
            // Trunk, last to first. `cur` holds d/d out[i] on entry.
            let mut cur: Vec<f32> = std::mem::take(&mut w.dz);
            for i in (0..nt).rev() {
                let tl = m.trunk[i];
                let l = tl.lin;
                {
                    let (dg, dbeta, db) = split_three(&mut w.grads, tl.g, tl.beta, l.b);
                    let grads = LnGrads { dg, dbeta, db };
                    ln_backward(
                        m.isa,
                        &mut cur[..n * l.output],
                        Some(w.out[i].as_slice()),
                        &w.xhat[i],
                        &w.rstd[i],
                        &p[tl.g],
                        n,
                        l.output,
                        Some(grads),
                    );
                }
                // dW = dpre^T @ input
                let (inp, ins): (*const f32, usize) =
                    if i == 0 { (w.x.as_ptr(), ti) } else { (w.out[i - 1].as_ptr(), l.input) };
                mm(
                    l.output,
                    l.input,
                    n,
                    w.grads[l.w].as_mut_ptr(),
                    l.input,
                    1,
                    false,
                    cur.as_ptr(),
                    1,
                    l.output,
                    inp,
                    ins,
                    1,
                );
                // d input = dpre @ W (for the first trunk layer only the encoder columns).
                let cols = if i == 0 { 2 * ew } else { l.input };
                mm(
                    n,
                    cols,
                    l.output,
                    w.dtmp.as_mut_ptr(),
                    cols,
                    1,
                    false,
                    cur.as_ptr(),
                    l.output,
                    1,
                    p[l.w].as_ptr(),
                    l.input,
                    1,
                );
                if i > 0 {
                    // next iteration's cur = dtmp (d/d out[i-1])
                    let len = n * cols;
                    if cur.len() < len {
                        cur.resize(len, 0.0);
                    }
                    cur[..len].copy_from_slice(&w.dtmp[..len]);
                }
            }
            w.dz = cur;
            // Encoders: dtmp = [n, 2*ew] = d/d(ho, ha).
            let d2 = 2 * ew;
            for (l1, l0, h1, inp, ind, col) in
                [(m.o1, m.o0, &w.h_o, &w.obs, od, 0usize), (m.a1, m.a0, &w.h_a, &w.act, ad, ew)]
            {
                let dptr = w.dtmp.as_mut_ptr().add(col);
                let dsl = std::slice::from_raw_parts_mut(dptr, n * d2 - col);
                dispatch!(m.isa, relu_back_colsum(dsl, d2, &w.x[col..], ti, n, &mut w.grads[l1.b]));
                mm(
                    l1.output,
                    l1.input,
                    n,
                    w.grads[l1.w].as_mut_ptr(),
                    l1.input,
                    1,
                    false,
                    dptr,
                    1,
                    d2,
                    h1.as_ptr(),
                    ew,
                    1,
                );
                mm(
                    n,
                    l1.input,
                    l1.output,
                    w.dh.as_mut_ptr(),
                    ew,
                    1,
                    false,
                    dptr,
                    d2,
                    1,
                    p[l1.w].as_ptr(),
                    l1.input,
                    1,
                );
                dispatch!(m.isa, relu_back_colsum(&mut w.dh, ew, h1, ew, n, &mut w.grads[l0.b]));
                mm(
                    l0.output,
                    l0.input,
                    n,
                    w.grads[l0.w].as_mut_ptr(),
                    l0.input,
                    1,
                    false,
                    w.dh.as_ptr(),
                    1,
                    ew,
                    inp.as_ptr(),
                    ind,
                    1,
                );
            }
        }
    }
}

fn split_two(v: &mut [Vec<f32>], a: usize, b: usize) -> (&mut [f32], &mut [f32]) {
    assert!(a != b);
    let pa: *mut Vec<f32> = &mut v[a];
    let pb: *mut Vec<f32> = &mut v[b];
    // SAFETY: distinct indices.
    unsafe { ((*pa).as_mut_slice(), (*pb).as_mut_slice()) }
}

fn split_three(v: &mut [Vec<f32>], a: usize, b: usize, c: usize) -> (&mut [f32], &mut [f32], &mut [f32]) {
    assert!(a != b && b != c && a != c);
    let pa: *mut Vec<f32> = &mut v[a];
    let pb: *mut Vec<f32> = &mut v[b];
    let pc: *mut Vec<f32> = &mut v[c];
    // SAFETY: distinct indices.
    unsafe { ((*pa).as_mut_slice(), (*pb).as_mut_slice(), (*pc).as_mut_slice()) }
}
