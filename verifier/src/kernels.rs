//! Numeric kernels: the packed matrix product of the forward pass and its gradient, and the
//! row-wise LayerNorm (+ ReLU) forward and backward that the trainer's fused training path
//! shares. Each has an AVX2/FMA version, selected at run time ([`Isa::detect`]), and a portable
//! one; both compute the same thing up to summation order.
//!
//! One file past 700 lines: each kernel sits beside its portable twin and the tests that hold them
//! equal.
#![allow(unsafe_code, reason = "the AVX2/FMA kernels: target-feature functions and intrinsics")]

/// Which instruction set the kernels use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// x86-64 AVX2 + FMA (checked at run time).
    Avx2Fma,
    /// Plain Rust, any CPU.
    Portable,
}

impl Isa {
    /// The best instruction set this CPU supports.
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                return Isa::Avx2Fma;
            }
        }
        Isa::Portable
    }

    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx2Fma => "avx2-fma",
            Isa::Portable => "portable",
        }
    }

    /// `self`, unless this CPU lacks it (then [`Isa::Portable`]): never runs an instruction the
    /// CPU does not have.
    pub(crate) fn checked(self) -> Isa {
        if self == Isa::Avx2Fma && Isa::detect() != Isa::Avx2Fma {
            Isa::Portable
        } else {
            self
        }
    }
}

/// `x` rounded up to a multiple of 8 (one AVX2 register of f32).
pub fn pad8(x: usize) -> usize {
    x.div_ceil(8) * 8
}

/// A weight matrix packed for `out[r][j] = init[r][j] + sum_i x[r][i] * w[i][j]`: `k`
/// contraction rows, output columns padded with zeros to `mp` (a multiple of 8).
#[derive(Clone, Debug)]
pub(crate) struct Packed {
    pub k: usize,
    pub mp: usize,
    w: Vec<f32>,
}

impl Packed {
    /// From a PyTorch `[out, in]` weight, for the forward pass (contract over `in`), keeping the
    /// input columns `cols` in this order.
    pub fn forward(w: &[f32], out: usize, inp: usize, cols: &[usize]) -> Packed {
        let mp = pad8(out);
        let mut v = vec![0f32; cols.len() * mp];
        for (i, &c) in cols.iter().enumerate() {
            for o in 0..out {
                v[i * mp + o] = w[o * inp + c];
            }
        }
        Packed { k: cols.len(), mp, w: v }
    }

    /// From a PyTorch `[out, in]` weight, for the backward pass (contract over `out`),
    /// producing the gradient w.r.t. the input columns `cols`.
    pub fn backward(w: &[f32], out: usize, inp: usize, cols: &[usize]) -> Packed {
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

/// `out (n rows x p.mp) = init (row stride init_stride; 0 broadcasts one row) + x (n rows, stride
/// xs, first p.k columns) @ p`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn gemm(
    isa: Isa,
    x: &[f32],
    xs: usize,
    n: usize,
    p: &Packed,
    init: &[f32],
    init_stride: usize,
    out: &mut [f32],
) {
    if n == 0 {
        return;
    }
    // Real asserts: the SIMD kernel reads and writes through raw pointers.
    assert!(xs >= p.k && x.len() >= (n - 1) * xs + p.k, "gemm: x too short");
    assert!(init.len() >= init_stride * (n - 1) + p.mp, "gemm: init too short");
    assert!(out.len() >= n * p.mp, "gemm: out too short");
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx2Fma {
        // SAFETY: the CPU has AVX2 + FMA (Isa::checked at construction); sizes asserted above.
        unsafe {
            x86::gemm(
                x.as_ptr(),
                xs,
                n,
                p.k,
                p.w.as_ptr(),
                p.mp,
                init.as_ptr(),
                init_stride,
                out.as_mut_ptr(),
            )
        };
        return;
    }
    let _ = isa;
    let mp = p.mp;
    for r in 0..n {
        let o = &mut out[r * mp..(r + 1) * mp];
        o.copy_from_slice(&init[r * init_stride..r * init_stride + mp]);
        for i in 0..p.k {
            let xv = x[r * xs + i];
            if xv == 0.0 {
                continue; // ReLU zeros: common, and skipping them is exact
            }
            for (oj, wj) in o.iter_mut().zip(&p.w[i * mp..(i + 1) * mp]) {
                *oj += xv * wj;
            }
        }
    }
}

/// Dot product with 8 partial sums (vectorises without `-ffast-math`).
pub(crate) fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut s = [0f32; 8];
    let n8 = a.len().min(b.len()) / 8 * 8;
    for (ca, cb) in a[..n8].chunks_exact(8).zip(b[..n8].chunks_exact(8)) {
        for l in 0..8 {
            s[l] += ca[l] * cb[l];
        }
    }
    let mut t = s.iter().sum::<f32>();
    for i in n8..a.len().min(b.len()) {
        t += a[i] * b[i];
    }
    t
}

/// Parameter gradients a LayerNorm backward accumulates (training): `dg += dl * xhat`,
/// `dbeta += dl`, and `db += d pre` (the bias of the linear before the norm).
pub struct LnGrads<'a> {
    pub dg: &'a mut [f32],
    pub dbeta: &'a mut [f32],
    pub db: &'a mut [f32],
}

fn check_rows(what: &str, len: usize, rows: usize, rs: usize, n: usize) {
    assert!(rows == 0 || len >= (rows - 1) * rs + n, "{what}: buffer too short for {rows} rows");
}

/// LayerNorm (biased variance) over `rows` rows of width `n = g.len()` at row stride `rs`,
/// optionally followed by ReLU: `pre += bias` (when given), `xhat = (pre - mean) * rstd`,
/// `out = act(xhat * g + beta)`; `rstd[r]` and `xhat` are kept for [`ln_backward`].
#[allow(clippy::too_many_arguments)]
pub fn ln_forward(
    isa: Isa,
    pre: &mut [f32],
    bias: Option<&[f32]>,
    xhat: &mut [f32],
    rstd: &mut [f32],
    out: &mut [f32],
    g: &[f32],
    beta: &[f32],
    eps: f32,
    rows: usize,
    rs: usize,
    relu: bool,
) {
    let n = g.len();
    assert!(rs >= n && beta.len() >= n && bias.is_none_or(|b| b.len() >= n) && rstd.len() >= rows);
    check_rows("ln_forward pre", pre.len(), rows, rs, n);
    check_rows("ln_forward xhat", xhat.len(), rows, rs, n);
    check_rows("ln_forward out", out.len(), rows, rs, n);
    let a = LnPtrs {
        pre: pre.as_mut_ptr(),
        bias: bias.map_or(std::ptr::null(), |b| b.as_ptr()),
        xhat: xhat.as_mut_ptr(),
        rstd: rstd.as_mut_ptr(),
        out: out.as_mut_ptr(),
        g: g.as_ptr(),
        beta: beta.as_ptr(),
    };
    // SAFETY: lengths asserted above; distinct slices do not overlap.
    unsafe { ln_forward_dispatch(isa, a, eps, n, rows, rs, relu) }
}

/// [`ln_forward`] in place, keeping no statistics (scoring).
#[allow(clippy::too_many_arguments)]
pub fn ln_inplace(
    isa: Isa,
    x: &mut [f32],
    g: &[f32],
    beta: &[f32],
    eps: f32,
    rows: usize,
    rs: usize,
    relu: bool,
) {
    let n = g.len();
    assert!(rs >= n && beta.len() >= n);
    check_rows("ln_inplace", x.len(), rows, rs, n);
    let p = x.as_mut_ptr();
    let a = LnPtrs {
        pre: p,
        bias: std::ptr::null(),
        xhat: std::ptr::null_mut(),
        rstd: std::ptr::null_mut(),
        out: p,
        g: g.as_ptr(),
        beta: beta.as_ptr(),
    };
    // SAFETY: length asserted; the kernel reads each element before writing it (raw pointers).
    unsafe { ln_forward_dispatch(isa, a, eps, n, rows, rs, relu) }
}

/// Backward of [`ln_forward`]: `d` holds d/d out on entry and d/d pre on exit. With
/// `relu_out` (the forward's output) the ReLU is differentiated too. `grads` accumulates the
/// parameter gradients (training); inference passes `None`.
#[allow(clippy::too_many_arguments)]
pub fn ln_backward(
    isa: Isa,
    d: &mut [f32],
    relu_out: Option<&[f32]>,
    xhat: &[f32],
    rstd: &[f32],
    g: &[f32],
    rows: usize,
    rs: usize,
    grads: Option<LnGrads<'_>>,
) {
    let n = g.len();
    assert!(rs >= n && rstd.len() >= rows);
    check_rows("ln_backward d", d.len(), rows, rs, n);
    check_rows("ln_backward xhat", xhat.len(), rows, rs, n);
    if let Some(o) = relu_out {
        check_rows("ln_backward out", o.len(), rows, rs, n);
    }
    let (dg, dbeta, db) = match grads {
        Some(LnGrads { dg, dbeta, db }) => {
            assert!(dg.len() >= n && dbeta.len() >= n && db.len() >= n);
            (dg.as_mut_ptr(), dbeta.as_mut_ptr(), db.as_mut_ptr())
        }
        None => (std::ptr::null_mut(), std::ptr::null_mut(), std::ptr::null_mut()),
    };
    let a = LnBackPtrs {
        d: d.as_mut_ptr(),
        out: relu_out.map_or(std::ptr::null(), |o| o.as_ptr()),
        xhat: xhat.as_ptr(),
        rstd: rstd.as_ptr(),
        g: g.as_ptr(),
        dg,
        dbeta,
        db,
    };
    // SAFETY: lengths asserted above; distinct slices do not overlap.
    unsafe { ln_backward_dispatch(isa, a, n, rows, rs) }
}

#[derive(Clone, Copy)]
struct LnPtrs {
    pre: *mut f32,
    bias: *const f32,
    /// null: do not keep xhat / rstd
    xhat: *mut f32,
    rstd: *mut f32,
    out: *mut f32,
    g: *const f32,
    beta: *const f32,
}

#[derive(Clone, Copy)]
struct LnBackPtrs {
    d: *mut f32,
    /// null: no ReLU
    out: *const f32,
    xhat: *const f32,
    rstd: *const f32,
    g: *const f32,
    /// null: no parameter gradients
    dg: *mut f32,
    dbeta: *mut f32,
    db: *mut f32,
}

unsafe fn ln_forward_dispatch(isa: Isa, a: LnPtrs, eps: f32, n: usize, rows: usize, rs: usize, relu: bool) {
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx2Fma {
        return match relu {
            true => x86::ln_forward::<true>(a, eps, n, rows, rs),
            false => x86::ln_forward::<false>(a, eps, n, rows, rs),
        };
    }
    let _ = isa;
    match relu {
        true => portable_ln_forward::<true>(a, eps, n, rows, rs),
        false => portable_ln_forward::<false>(a, eps, n, rows, rs),
    }
}

unsafe fn ln_backward_dispatch(isa: Isa, a: LnBackPtrs, n: usize, rows: usize, rs: usize) {
    let relu = !a.out.is_null();
    let acc = !a.dg.is_null();
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx2Fma {
        return match (relu, acc) {
            (true, true) => x86::ln_backward::<true, true>(a, n, rows, rs),
            (true, false) => x86::ln_backward::<true, false>(a, n, rows, rs),
            (false, true) => x86::ln_backward::<false, true>(a, n, rows, rs),
            (false, false) => x86::ln_backward::<false, false>(a, n, rows, rs),
        };
    }
    let _ = isa;
    match (relu, acc) {
        (true, true) => portable_ln_backward::<true, true>(a, n, rows, rs),
        (true, false) => portable_ln_backward::<true, false>(a, n, rows, rs),
        (false, true) => portable_ln_backward::<false, true>(a, n, rows, rs),
        (false, false) => portable_ln_backward::<false, false>(a, n, rows, rs),
    }
}

unsafe fn portable_ln_forward<const RELU: bool>(a: LnPtrs, eps: f32, n: usize, rows: usize, rs: usize) {
    let inv_n = 1.0 / n as f32;
    for r in 0..rows {
        let p = a.pre.add(r * rs);
        let mut acc = [0f32; 8];
        for k in 0..n {
            if !a.bias.is_null() {
                *p.add(k) += *a.bias.add(k);
            }
            acc[k % 8] += *p.add(k);
        }
        let mean = acc.iter().sum::<f32>() * inv_n;
        let mut acc = [0f32; 8];
        for k in 0..n {
            let c = *p.add(k) - mean;
            acc[k % 8] += c * c;
        }
        let rstd = 1.0 / (acc.iter().sum::<f32>() * inv_n + eps).sqrt();
        if !a.rstd.is_null() {
            *a.rstd.add(r) = rstd;
        }
        let o = a.out.add(r * rs);
        for k in 0..n {
            let h = (*p.add(k) - mean) * rstd;
            if !a.xhat.is_null() {
                *a.xhat.add(r * rs + k) = h;
            }
            let v = h * *a.g.add(k) + *a.beta.add(k);
            // `v < 0 ? 0 : v` (not max) so a NaN input stays NaN.
            *o.add(k) = if RELU && v < 0.0 { 0.0 } else { v };
        }
    }
}

unsafe fn portable_ln_backward<const RELU: bool, const ACC: bool>(
    a: LnBackPtrs,
    n: usize,
    rows: usize,
    rs: usize,
) {
    let inv_n = 1.0 / n as f32;
    for r in 0..rows {
        let d = a.d.add(r * rs);
        let x = a.xhat.add(r * rs);
        let (mut s1, mut s2) = ([0f32; 8], [0f32; 8]);
        for k in 0..n {
            let mut dl = *d.add(k);
            if RELU && *a.out.add(r * rs + k) <= 0.0 {
                dl = 0.0;
            }
            if ACC {
                *a.dg.add(k) += dl * *x.add(k);
                *a.dbeta.add(k) += dl;
            }
            let dxh = dl * *a.g.add(k);
            *d.add(k) = dxh;
            s1[k % 8] += dxh;
            s2[k % 8] += dxh * *x.add(k);
        }
        let m1 = s1.iter().sum::<f32>() * inv_n;
        let m2 = s2.iter().sum::<f32>() * inv_n;
        let rstd = *a.rstd.add(r);
        for k in 0..n {
            let v = rstd * (*d.add(k) - m1 - *x.add(k) * m2);
            *d.add(k) = v;
            if ACC {
                *a.db.add(k) += v;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
// The register tiles (`acc[r][b]`) are indexed by position on purpose: the loops unroll into
// fixed registers.
#[allow(clippy::needless_range_loop)]
mod x86 {
    use super::{LnBackPtrs, LnPtrs};
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx2,fma")]
    unsafe fn hsum(v: __m256) -> f32 {
        let lo = _mm256_castps256_ps128(v);
        let hi = _mm256_extractf128_ps(v, 1);
        let s = _mm_add_ps(lo, hi);
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        let s = _mm_add_ss(s, _mm_shuffle_ps(s, s, 1));
        _mm_cvtss_f32(s)
    }

    /// R rows x (8*B) columns tile starting at column c.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    #[allow(clippy::too_many_arguments)]
    unsafe fn tile<const R: usize, const B: usize>(
        x: *const f32,
        xs: usize,
        k: usize,
        w: *const f32,
        mp: usize,
        init: *const f32,
        is: usize,
        out: *mut f32,
        c: usize,
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
    #[allow(clippy::too_many_arguments)]
    unsafe fn rows<const R: usize, const B: usize>(
        x: *const f32,
        xs: usize,
        k: usize,
        w: *const f32,
        mp: usize,
        init: *const f32,
        is: usize,
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

    /// See `super::gemm`.
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn gemm(
        x: *const f32,
        xs: usize,
        n: usize,
        k: usize,
        w: *const f32,
        mp: usize,
        init: *const f32,
        is: usize,
        out: *mut f32,
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

    /// See `super::ln_forward`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn ln_forward<const RELU: bool>(a: LnPtrs, eps: f32, n: usize, rows: usize, rs: usize) {
        let n8 = n - n % 8;
        let inv_n = 1.0 / n as f32;
        let zero = _mm256_setzero_ps();
        for r in 0..rows {
            let pp = a.pre.add(r * rs);
            let mut acc = zero;
            let mut k = 0;
            while k < n8 {
                let mut v = _mm256_loadu_ps(pp.add(k));
                if !a.bias.is_null() {
                    v = _mm256_add_ps(v, _mm256_loadu_ps(a.bias.add(k)));
                    _mm256_storeu_ps(pp.add(k), v);
                }
                acc = _mm256_add_ps(acc, v);
                k += 8;
            }
            let mut s = hsum(acc);
            for k in n8..n {
                if !a.bias.is_null() {
                    *pp.add(k) += *a.bias.add(k);
                }
                s += *pp.add(k);
            }
            let mean = s * inv_n;
            let mv = _mm256_set1_ps(mean);
            let mut acc = zero;
            let mut k = 0;
            while k < n8 {
                let c = _mm256_sub_ps(_mm256_loadu_ps(pp.add(k)), mv);
                acc = _mm256_fmadd_ps(c, c, acc);
                k += 8;
            }
            let mut q = hsum(acc);
            for k in n8..n {
                let c = *pp.add(k) - mean;
                q += c * c;
            }
            let rstd = 1.0 / (q * inv_n + eps).sqrt();
            if !a.rstd.is_null() {
                *a.rstd.add(r) = rstd;
            }
            let rv = _mm256_set1_ps(rstd);
            let op = a.out.add(r * rs);
            let xp = if a.xhat.is_null() { std::ptr::null_mut() } else { a.xhat.add(r * rs) };
            let mut k = 0;
            while k < n8 {
                let h = _mm256_mul_ps(_mm256_sub_ps(_mm256_loadu_ps(pp.add(k)), mv), rv);
                if !xp.is_null() {
                    _mm256_storeu_ps(xp.add(k), h);
                }
                let mut o = _mm256_fmadd_ps(h, _mm256_loadu_ps(a.g.add(k)), _mm256_loadu_ps(a.beta.add(k)));
                if RELU {
                    // max(0, o) returns its second operand when one is NaN: NaN stays NaN.
                    o = _mm256_max_ps(zero, o);
                }
                _mm256_storeu_ps(op.add(k), o);
                k += 8;
            }
            for k in n8..n {
                let h = (*pp.add(k) - mean) * rstd;
                if !xp.is_null() {
                    *xp.add(k) = h;
                }
                let o = h * *a.g.add(k) + *a.beta.add(k);
                *op.add(k) = if RELU && o < 0.0 { 0.0 } else { o };
            }
        }
    }

    /// See `super::ln_backward`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn ln_backward<const RELU: bool, const ACC: bool>(
        a: LnBackPtrs,
        n: usize,
        rows: usize,
        rs: usize,
    ) {
        let n8 = n - n % 8;
        let inv_n = 1.0 / n as f32;
        let zero = _mm256_setzero_ps();
        for r in 0..rows {
            let dp = a.d.add(r * rs);
            let xp = a.xhat.add(r * rs);
            let mut a1 = zero;
            let mut a2 = zero;
            let mut k = 0;
            while k < n8 {
                let mut dl = _mm256_loadu_ps(dp.add(k));
                if RELU {
                    let m = _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_loadu_ps(a.out.add(r * rs + k)), zero);
                    dl = _mm256_and_ps(dl, m);
                }
                let x = _mm256_loadu_ps(xp.add(k));
                if ACC {
                    _mm256_storeu_ps(a.dg.add(k), _mm256_fmadd_ps(dl, x, _mm256_loadu_ps(a.dg.add(k))));
                    _mm256_storeu_ps(a.dbeta.add(k), _mm256_add_ps(dl, _mm256_loadu_ps(a.dbeta.add(k))));
                }
                let dxh = _mm256_mul_ps(dl, _mm256_loadu_ps(a.g.add(k)));
                _mm256_storeu_ps(dp.add(k), dxh);
                a1 = _mm256_add_ps(a1, dxh);
                a2 = _mm256_fmadd_ps(dxh, x, a2);
                k += 8;
            }
            let (mut s1, mut s2) = (hsum(a1), hsum(a2));
            for k in n8..n {
                let mut dl = *dp.add(k);
                if RELU && *a.out.add(r * rs + k) <= 0.0 {
                    dl = 0.0;
                }
                let x = *xp.add(k);
                if ACC {
                    *a.dg.add(k) += dl * x;
                    *a.dbeta.add(k) += dl;
                }
                let dxh = dl * *a.g.add(k);
                *dp.add(k) = dxh;
                s1 += dxh;
                s2 += dxh * x;
            }
            let (m1, m2) = (s1 * inv_n, s2 * inv_n);
            let (m1v, m2v) = (_mm256_set1_ps(m1), _mm256_set1_ps(m2));
            let rstd = *a.rstd.add(r);
            let rv = _mm256_set1_ps(rstd);
            let mut k = 0;
            while k < n8 {
                let x = _mm256_loadu_ps(xp.add(k));
                let t = _mm256_fnmadd_ps(x, m2v, _mm256_sub_ps(_mm256_loadu_ps(dp.add(k)), m1v));
                let v = _mm256_mul_ps(rv, t);
                _mm256_storeu_ps(dp.add(k), v);
                if ACC {
                    _mm256_storeu_ps(a.db.add(k), _mm256_add_ps(v, _mm256_loadu_ps(a.db.add(k))));
                }
                k += 8;
            }
            for k in n8..n {
                let v = rstd * (*dp.add(k) - m1 - *xp.add(k) * m2);
                *dp.add(k) = v;
                if ACC {
                    *a.db.add(k) += v;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| (((i as u32).wrapping_mul(2654435761).wrapping_add(seed)) % 1000) as f32 / 250.0 - 2.0)
            .collect()
    }

    #[test]
    fn layer_norm_kernels_agree_across_instruction_sets_and_strides() {
        for &(n, rs) in &[(8usize, 8usize), (13, 16), (64, 64), (5, 7)] {
            let rows = 3;
            let g = data(n, 1);
            let beta = data(n, 2);
            let bias = data(n, 3);
            let mut res = Vec::new();
            for isa in [Isa::Portable, Isa::detect()] {
                let mut pre = data(rows * rs, 4);
                let (mut xhat, mut out, mut rstd) =
                    (vec![0.0; rows * rs], vec![0.0; rows * rs], vec![0.0; rows]);
                ln_forward(
                    isa,
                    &mut pre,
                    Some(bias.as_slice()),
                    &mut xhat,
                    &mut rstd,
                    &mut out,
                    &g,
                    &beta,
                    1e-5,
                    rows,
                    rs,
                    true,
                );
                let mut d = data(rows * rs, 5);
                let (mut dg, mut dbeta, mut db) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
                let grads = LnGrads { dg: &mut dg, dbeta: &mut dbeta, db: &mut db };
                ln_backward(isa, &mut d, Some(out.as_slice()), &xhat, &rstd, &g, rows, rs, Some(grads));
                let mut inplace = data(rows * rs, 4);
                for r in 0..rows {
                    for k in 0..n {
                        inplace[r * rs + k] += bias[k];
                    }
                }
                ln_inplace(isa, &mut inplace, &g, &beta, 1e-5, rows, rs, true);
                res.push((out, d, dg, dbeta, db, inplace));
            }
            let close =
                |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + y.abs()));
            let (p, s) = (&res[0], &res[1]);
            for r in 0..rows {
                let row = r * rs..r * rs + n;
                assert!(close(&p.0[row.clone()], &s.0[row.clone()]), "forward n={n}");
                assert!(close(&p.1[row.clone()], &s.1[row.clone()]), "backward n={n}");
                assert!(close(&p.0[row.clone()], &p.5[row.clone()]), "in place n={n}");
            }
            assert!(close(&p.2, &s.2) && close(&p.3, &s.3) && close(&p.4, &s.4), "param grads n={n}");
            // LayerNorm output has zero mean / unit variance before the affine (checked on xhat
            // implicitly through ReLU(xhat*g+beta): at least one value survives).
            assert!(p.0.iter().any(|v| *v > 0.0));
        }
    }
}
