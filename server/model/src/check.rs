//! The field validators of scene sections: every value is checked for presence, finiteness and
//! range, and an error names the field by its dotted path (`mesh.semi_axes_m`). Used by `scene`
//! and by the model families' own sections.

use glam::DVec3;

use crate::ModelError;

/// A finite value satisfying `ok`, described by `expect` in the error.
pub(crate) fn checked(
    field: &str,
    v: f64,
    ok: impl Fn(f64) -> bool,
    expect: &str,
) -> Result<f64, ModelError> {
    if !v.is_finite() {
        return Err(ModelError::field(
            field,
            format!("must be a finite number, got {v}"),
        ));
    }
    if !ok(v) {
        return Err(ModelError::field(
            field,
            format!("must be {expect}, got {v}"),
        ));
    }
    Ok(v)
}

/// `v`, or the error "is required but missing".
pub(crate) fn required<T>(field: &str, v: Option<T>) -> Result<T, ModelError> {
    v.ok_or_else(|| ModelError::field(field, "is required but missing"))
}

/// A finite value > 0.
pub(crate) fn positive(field: &str, v: f64) -> Result<f64, ModelError> {
    checked(field, v, |x| x > 0.0, "> 0")
}

/// A finite value >= 0.
pub(crate) fn non_negative(field: &str, v: f64) -> Result<f64, ModelError> {
    checked(field, v, |x| x >= 0.0, ">= 0")
}

/// Three finite values > 0, times `unit` (to metres).
pub(crate) fn positive_vec(field: &str, v: [f64; 3], unit: f64) -> Result<DVec3, ModelError> {
    for x in v {
        positive(field, x)?;
    }
    Ok(DVec3::from_array(v) * unit)
}

/// An integer in `lo..=hi`.
pub(crate) fn int_in(field: &str, v: i64, lo: i64, hi: i64) -> Result<usize, ModelError> {
    if v < lo || v > hi {
        return Err(ModelError::field(
            field,
            format!("must be an integer in {lo}..={hi}, got {v}"),
        ));
    }
    Ok(v as usize)
}

/// A finite vector with every component checked and a bounded magnitude.
pub(crate) fn bounded_vec(field: &str, v: [f64; 3], max: f64) -> Result<DVec3, ModelError> {
    for x in v {
        checked(field, x, |_| true, "finite")?;
    }
    let d = DVec3::from_array(v);
    if d.length() > max {
        return Err(ModelError::field(
            field,
            format!("magnitude {:.3e} exceeds the {max:.0e} limit", d.length()),
        ));
    }
    Ok(d)
}
