//! Turning what Python passes (numpy arrays, torch tensors, DLPack producers, lists, ints) into
//! slices the verifier core reads: a C-contiguous float32 numpy array is read in place (no copy);
//! anything else goes through `ufops._arrays.as_numpy` (torch tensors share their memory through
//! `Tensor.numpy()` on the CPU, other devices are copied to it) and is copied only if strided.

use std::borrow::Cow;

use numpy::{
    PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;

/// `x` as a numpy array: itself when it is one, else converted by the Python layer
/// (`dtype` is what lists and scalars become).
fn as_ndarray<'py>(x: &Bound<'py, PyAny>, dtype: &str) -> PyResult<Bound<'py, PyUntypedArray>> {
    if let Ok(a) = x.cast::<PyUntypedArray>() {
        return Ok(a.clone());
    }
    let converted = x.py().import("ufops._arrays")?.getattr("as_numpy")?.call1((x, dtype))?;
    converted
        .cast_into::<PyUntypedArray>()
        .map_err(|_| PyTypeError::new_err("ufops._arrays.as_numpy did not return an ndarray"))
}

pub fn shape_str(shape: &[usize]) -> String {
    match shape {
        [one] => format!("({one},)"),
        _ => format!("({})", shape.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")),
    }
}

/// A float32 array argument, borrowed read-only.
/// `expected` (the accepted shapes, for the error message) is only called on a failure.
pub fn f32_array<'py>(
    x: &Bound<'py, PyAny>,
    name: &str,
    expected: impl FnOnce() -> String,
) -> PyResult<PyReadonlyArrayDyn<'py, f32>> {
    let a = as_ndarray(x, "float32")?;
    match a.cast::<PyArrayDyn<f32>>() {
        Ok(f) => Ok(f.readonly()),
        Err(_) => Err(PyTypeError::new_err(format!(
            "{name} must be a float32 array of shape {}; got dtype {} with shape {}",
            expected(),
            a.dtype(),
            shape_str(a.shape())
        ))),
    }
}

/// The array's elements in C order: borrowed when C-contiguous, else copied.
pub fn values<'a>(a: &'a PyReadonlyArrayDyn<'_, f32>) -> Cow<'a, [f32]> {
    match a.as_slice() {
        Ok(s) => Cow::Borrowed(s),
        Err(_) => Cow::Owned(a.as_array().iter().copied().collect()),
    }
}

/// The diffusion step(s): an int (the same step for every row) or `b` non-negative integers.
pub fn steps(t: &Bound<'_, PyAny>, b: usize) -> PyResult<Vec<u32>> {
    let check = |v: i64| -> PyResult<u32> {
        u32::try_from(v)
            .map_err(|_| PyValueError::new_err(format!("t must be a non-negative step below 2^32; got {v}")))
    };
    if let Ok(v) = t.extract::<i64>() {
        return Ok(vec![check(v)?; b]);
    }
    let a = as_ndarray(t, "int64")?;
    let kind = a.dtype().kind();
    if kind != b'i' && kind != b'u' {
        return Err(PyTypeError::new_err(format!(
            "t must be an int or an integer array of shape ({b},); got dtype {}",
            a.dtype()
        )));
    }
    if a.shape() != [b] {
        return Err(PyValueError::new_err(format!(
            "t must be an int or an integer array of shape ({b},); got shape {}",
            shape_str(a.shape())
        )));
    }
    let as_i64 = a.call_method1("astype", ("int64",))?;
    let arr =
        as_i64.cast::<PyArrayDyn<i64>>().map_err(|_| PyTypeError::new_err("t: astype(int64) failed"))?;
    let ro = arr.readonly();
    ro.as_array().iter().map(|&v| check(v)).collect()
}
