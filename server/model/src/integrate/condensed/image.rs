//! A prepared following region as bytes, and back (issue 48 s2: the region cache stored on
//! disk, [`crate::integrate::follow`]).
//!
//! The image holds what a preparation computes and a reconstruction cannot get cheaply: the
//! condensed far stiffness `S`, the far map and its rows, the tick matrix's pattern, its
//! fill-reducing ordering and its factor (single and half precision), and the prepared contact
//! columns. Everything else (the split, its numbering, the active elements' model, the
//! factor's symbolic analysis under the stored ordering) is rebuilt from the body and the
//! region. A reconstructed region steps bit for bit like the one written.
//!
//! Format 3 (2026-11-29) stores the pattern, the ordering and the map's rows, which format 2
//! derived again on every read (assembling the tick matrix, METIS, the mesh's boundary): a
//! 29 MB tile of the 100 000-tet LV read back in about 200 ms with format 2
//! (docs/benchmarks.md, "Tiles read back").
//!
//! Layout (native byte order, which the format number's bytes also tell): the magic
//! `HAPTTILE`, the format number [`TILE_IMAGE_FORMAT`] (u32), the caller's 32-byte key, the
//! centre (3 f64) and the step (f64), then the arrays, each as its element count (u64) and its
//! elements, and last the BLAKE3 hash of everything before it.
//!
//! Owns: the image's layout and its checks. May use: [`super`].

use faer::sparse::{SymbolicSparseColMat, SymbolicSparseColMatRef};

use super::build::{
    MapRows, Selection, Split, TickFactor, check_region, number_equations, select_elements,
};
use super::*;
use crate::linalg::ordering::symbolic_cholesky_in_order;

/// Version of the image layout and of the preparation it stores. Raise it whenever either
/// changes (a field, an array, the condensation's or the factor's arithmetic): an image of
/// another number is refused, so a cache never serves a region the code would not build.
pub const TILE_IMAGE_FORMAT: u32 = 3;

const MAGIC: &[u8; 8] = b"HAPTTILE";
const HASH_BYTES: usize = 32;

/// Appends arrays to an image.
struct Writer(Vec<u8>);

impl Writer {
    fn raw(&mut self, bytes: &[u8]) {
        self.0.extend_from_slice(bytes);
    }

    fn array<T: bytemuck::Pod>(&mut self, values: &[T]) {
        self.raw(&(values.len() as u64).to_ne_bytes());
        self.raw(bytemuck::cast_slice(values));
    }
}

/// Reads an image's fields in order; every read is bounds-checked.
struct Reader<'a> {
    bytes: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], ModelError> {
        if n > self.bytes.len() {
            return Err(bad("is truncated"));
        }
        let (head, rest) = self.bytes.split_at(n);
        self.bytes = rest;
        Ok(head)
    }

    fn u64(&mut self) -> Result<u64, ModelError> {
        let b = self.take(8)?;
        Ok(u64::from_ne_bytes(
            b.try_into().map_err(|_| bad("is truncated"))?,
        ))
    }

    fn f64(&mut self) -> Result<f64, ModelError> {
        self.u64().map(f64::from_bits)
    }

    fn array<T: bytemuck::Pod>(&mut self) -> Result<Vec<T>, ModelError> {
        let len = usize::try_from(self.u64()?).map_err(|_| bad("holds an absurd length"))?;
        let bytes = len
            .checked_mul(std::mem::size_of::<T>())
            .ok_or_else(|| bad("holds an absurd length"))?;
        let src = self.take(bytes)?;
        let mut values = vec![T::zeroed(); len];
        bytemuck::cast_slice_mut::<T, u8>(&mut values).copy_from_slice(src);
        Ok(values)
    }
}

fn bad(what: &str) -> ModelError {
    ModelError::InvalidInput(format!("region image {what}"))
}

/// `values` as u32, or an error for a region too large for the image's 32-bit indices.
fn narrow(values: &[usize]) -> Result<Vec<u32>, ModelError> {
    values
        .iter()
        .map(|&v| u32::try_from(v))
        .collect::<Result<_, _>>()
        .map_err(|_| {
            ModelError::InvalidInput("the region is too large for an image's 32-bit indices".into())
        })
}

/// Rows of `m` equations take 16 bits in an image when they fit (every tile of the shipped
/// scenes: 3 500 equations on the 100 000-tet LV), else 32.
fn short_rows(m: usize) -> bool {
    m <= 1 << 16
}

/// Appends the lower-triangle pattern `pattern` (`m x m`): its column pointers (u32) and its
/// row indices ([`short_rows`]).
fn write_pattern(
    w: &mut Writer,
    pattern: SymbolicSparseColMatRef<'_, usize>,
) -> Result<(), ModelError> {
    w.array(&narrow(pattern.col_ptr())?);
    let rows = pattern.row_idx();
    if short_rows(pattern.nrows()) {
        w.array(&rows.iter().map(|&r| r as u16).collect::<Vec<_>>());
    } else {
        w.array(&narrow(rows)?);
    }
    Ok(())
}

/// The lower-triangle pattern of an `m x m` matrix that [`write_pattern`] appended,
/// checked (pointers increasing from 0 to the index count, rows strictly increasing within a
/// column from its diagonal on, below `m`), so that faer's analysis gets a valid pattern
/// from any bytes.
fn read_pattern(m: usize, r: &mut Reader<'_>) -> Result<SymbolicSparseColMat<usize>, ModelError> {
    let col_ptr: Vec<u32> = r.array()?;
    let row_idx: Vec<u32> = if short_rows(m) {
        r.array::<u16>()?.into_iter().map(u32::from).collect()
    } else {
        r.array()?
    };
    let wrong = || bad("does not fit the body's split (tick matrix pattern)");
    if col_ptr.len() != m + 1
        || col_ptr[0] != 0
        || col_ptr[m] as usize != row_idx.len()
        || col_ptr.windows(2).any(|w| w[0] > w[1])
    {
        return Err(wrong());
    }
    for (j, w) in col_ptr.windows(2).enumerate() {
        let rows = &row_idx[w[0] as usize..w[1] as usize];
        let ordered = rows.windows(2).all(|p| p[0] < p[1]);
        if !ordered
            || rows.first().is_some_and(|&r| (r as usize) < j)
            || rows.last().is_some_and(|&r| r as usize >= m)
        {
            return Err(wrong());
        }
    }
    let widen = |v: Vec<u32>| v.into_iter().map(|x| x as usize).collect::<Vec<_>>();
    Ok(SymbolicSparseColMat::new_checked(
        m,
        m,
        widen(col_ptr),
        None,
        widen(row_idx),
    ))
}

impl CondensedSolver {
    /// This region as bytes, tagged with `key` (the caller's digest of the body, the region's
    /// parameters and the touchable nodes: [`Self::from_image`] refuses an image of another
    /// key). Only a one-ball following region without a far factor or an entry factor has an
    /// image (a tile: [`ActiveRegion::follow`], [`Self::trim_for_tiles`]); about its
    /// [`Self::memory_bytes`].
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for a region that is not such a tile, or one too large for
    /// the image's 32-bit indices.
    pub fn to_image(&self, key: &[u8; 32]) -> Result<Vec<u8>, ModelError> {
        let sys = &self.system;
        if !self.params.region.follow
            || sys.far.llt.is_some()
            || sys.entry.is_some()
            || self.params.balls.centres().len() != 1
        {
            return Err(ModelError::InvalidInput(
                "only a one-ball following region without a far or entry factor has an image"
                    .into(),
            ));
        }
        let schur = unpack_symmetric(&sys.schur, sys.gamma_dof.len());
        let a_lower = self
            .tick_matrix_parts(&schur)
            .lower(self.params.region.stiffness_margin)?;
        let pattern = a_lower.symbolic();
        let forward: Vec<usize> = match sys.symbolic.perm() {
            Some(p) => p.arrays().0.to_vec(),
            None => (0..sys.eq_dof.len()).collect(),
        };
        // The reconstruction analyses the stored pattern (of `S` in single precision) under the
        // stored ordering; it must give this region's analysis.
        let again = symbolic_cholesky_in_order(pattern, Side::Lower, &forward)?;
        if again.len_val() != sys.symbolic.len_val() {
            return Err(ModelError::InvalidInput(
                "the region's tick factor cannot be rebuilt from its stored pattern".into(),
            ));
        }
        let mut w = Writer(Vec::with_capacity(self.memory_bytes() + 4096));
        w.raw(MAGIC);
        w.raw(&TILE_IMAGE_FORMAT.to_ne_bytes());
        w.raw(key);
        let c = self.params.region.centre_m;
        for v in [c.x, c.y, c.z, self.params.h] {
            w.raw(&v.to_bits().to_ne_bytes());
        }
        write_pattern(&mut w, pattern)?;
        w.array(&narrow(&forward)?);
        w.array(&sys.schur);
        w.array(&sys.factor);
        match &sys.half {
            Some(h) => {
                let (scale, inv_diag, node_start, triangles, values) = h.to_parts();
                w.array(&[1u8]);
                w.array(&scale);
                w.array(&inv_diag);
                w.array(&node_start);
                w.array(&triangles);
                w.array(&values);
            }
            None => w.array::<u8>(&[]),
        }
        w.array(&narrow(&sys.map_dofs)?);
        w.array(&sys.surface_rows);
        w.array(&sys.map);
        w.array(&self.contact.col);
        w.array(&self.contact.z);
        let hash = blake3::hash(&w.0);
        w.raw(hash.as_bytes());
        Ok(w.0)
    }

    /// The region [`Self::to_image`] wrote into `bytes`, rebuilt over `body` and `mesh` (the
    /// ones it was prepared on) as the following `region` (its centre the image's) with
    /// step `dt_s` (s): the split and the symbolic analysis (of the stored pattern, in the
    /// stored order) recomputed, the numeric arrays read. Steps bit for bit as the region
    /// written. Costs the active elements' model, the factor's symbolic analysis and a pass
    /// over the bytes (about 50 ms for a 29 MB tile of the 100 000-tet LV, docs/benchmarks.md,
    /// "Tiles read back").
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] naming what is wrong when `bytes` is not such an image
    /// (damaged: its hash; truncated), was written with another `key`, another format
    /// ([`TILE_IMAGE_FORMAT`]), centre or step, or does not fit the split the body gives;
    /// the region's own errors as [`Self::new`].
    pub fn from_image(
        body: &FemModel,
        mesh: &TetMesh,
        region: ActiveRegion,
        dt_s: f64,
        key: &[u8; 32],
        bytes: &[u8],
    ) -> Result<Self, ModelError> {
        let mut r = open_image(bytes, key, region.centre_m, dt_s)?;
        let region = ActiveRegion {
            follow: true,
            ..region
        };
        check_region(body, &region)?;
        let balls = RegionBalls::one(region.centre_m);
        let Selection {
            active_tets,
            active,
            node_active,
            node_far,
            ..
        } = select_elements(body, mesh, &region, &balls, false)?;
        let num = number_equations(body, &node_active, &node_far);
        let (g, m) = (num.gamma_dof.len(), num.eq_dof.len());
        let pattern = read_pattern(m, &mut r)?;
        let forward: Vec<u32> = r.array()?;
        let forward: Vec<usize> = forward.into_iter().map(|k| k as usize).collect();
        let symbolic = symbolic_cholesky_in_order(pattern.as_ref(), Side::Lower, &forward)
            .map_err(|_| bad("does not fit the body's split (ordering)"))?;
        let schur: Vec<f32> = r.array()?;
        if schur.len() != g * (g + 1) / 2 {
            return Err(bad("does not fit the body's split (interface size)"));
        }
        let tick = read_factors(&mut r, symbolic)?;
        let map_dofs: Vec<u32> = r.array()?;
        let rows = MapRows::read_back(&num, &map_dofs, r.array()?)
            .ok_or_else(|| bad("does not fit the body's split (far map rows)"))?;
        let split = Split::new(body, active_tets, active, node_active, num);
        let (map, contact) = read_map_and_contact(&mut r, &rows, g, m, body.node_count())?;
        let system = split.into_system(schur, tick, rows, map, None, Vec::new());
        let mut solver = Self::assemble(system, region, balls, dt_s, body.node_count());
        solver.contact = contact;
        Ok(solver)
    }

    /// The tick matrix's parts of this region with `schur` (its `S` row-major,
    /// [`unpack_symmetric`]).
    pub(super) fn tick_matrix_parts<'a>(&'a self, schur: &'a [f64]) -> TickMatrixParts<'a> {
        let sys = &self.system;
        TickMatrixParts {
            active: &sys.active,
            material: *sys.active.material(),
            eq: &sys.eq,
            gamma_dof: &sys.gamma_dof,
            schur,
            ball: ball_of(
                &self.params.balls,
                self.params.region.radius_m,
                sys.active.rest(),
                &sys.gamma_dof,
            ),
            mass: &sys.mass,
            h: self.params.h,
        }
    }
}

/// Checks an image's frame (length, magic, format, hash, `key`, centre `centre_m` and step
/// `dt_s`); the reader after it.
fn open_image<'a>(
    bytes: &'a [u8],
    key: &[u8; 32],
    centre_m: DVec3,
    dt_s: f64,
) -> Result<Reader<'a>, ModelError> {
    if bytes.len() < MAGIC.len() + 4 + HASH_BYTES {
        return Err(bad("is truncated"));
    }
    let (body_bytes, hash) = bytes.split_at(bytes.len() - HASH_BYTES);
    let mut r = Reader { bytes: body_bytes };
    read_format(&mut r)?;
    if blake3::hash(body_bytes).as_bytes() != hash {
        return Err(bad("is damaged (its BLAKE3 hash does not match)"));
    }
    read_identity(&mut r, key, centre_m, dt_s)?;
    Ok(r)
}

/// Bytes of an image's header: the magic, the format number, the key, the centre and the
/// step ([`CondensedSolver::check_image_header`]).
pub const TILE_IMAGE_HEADER_BYTES: usize = 8 + 4 + HASH_BYTES + 4 * 8;

impl CondensedSolver {
    /// Whether `head`, the first [`TILE_IMAGE_HEADER_BYTES`] bytes of an image (or more),
    /// begins an image of this format written with `key` for the centre `centre_m` and step
    /// `dt_s`: [`Self::from_image`]'s frame checks without the arrays and the hash, for a
    /// fill of the region cache that leaves the files it finds unread (a session reading
    /// one still checks all of it).
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] naming what differs, as [`Self::from_image`].
    pub fn check_image_header(
        head: &[u8],
        key: &[u8; 32],
        centre_m: DVec3,
        dt_s: f64,
    ) -> Result<(), ModelError> {
        let mut r = Reader { bytes: head };
        read_format(&mut r)?;
        read_identity(&mut r, key, centre_m, dt_s)
    }
}

/// Reads and checks the magic and the format number.
fn read_format(r: &mut Reader<'_>) -> Result<(), ModelError> {
    if r.take(MAGIC.len())? != MAGIC {
        return Err(bad("is not a region image (no HAPTTILE magic)"));
    }
    let format = u32::from_ne_bytes(r.take(4)?.try_into().map_err(|_| bad("is truncated"))?);
    if format != TILE_IMAGE_FORMAT {
        return Err(ModelError::InvalidInput(format!(
            "region image has format {format}, this build reads {TILE_IMAGE_FORMAT} (written \
             by another version)"
        )));
    }
    Ok(())
}

/// Reads and checks the key, the centre and the step.
fn read_identity(
    r: &mut Reader<'_>,
    key: &[u8; 32],
    centre_m: DVec3,
    dt_s: f64,
) -> Result<(), ModelError> {
    if r.take(HASH_BYTES)? != key {
        return Err(bad(
            "was written for another body, region or step (its key differs)",
        ));
    }
    let centre = DVec3::new(r.f64()?, r.f64()?, r.f64()?);
    let h = r.f64()?;
    if centre.to_array().map(f64::to_bits) != centre_m.to_array().map(f64::to_bits)
        || h.to_bits() != dt_s.to_bits()
    {
        return Err(bad("has another centre or step than asked"));
    }
    Ok(())
}

/// The tick factor on its rebuilt analysis `symbolic`: the sweep rebuilt, the factor's
/// values read.
fn read_factors(
    r: &mut Reader<'_>,
    symbolic: SymbolicCholesky<usize>,
) -> Result<TickFactor, ModelError> {
    let sweep = SupernodalSolve::new(&symbolic);
    let factor: Vec<f32> = r.array()?;
    let half = match r.array::<u8>()?.as_slice() {
        [] => None,
        [1] => {
            let arrays = (r.array()?, r.array()?, r.array()?, r.array()?, r.array()?);
            let half = sweep
                .as_ref()
                .and_then(|s| s.half_factor_from_parts(arrays))
                .ok_or_else(|| bad("does not fit the body's split (half factor)"))?;
            Some(half)
        }
        _ => return Err(bad("has an unknown factor flag")),
    };
    let trimmed = factor.is_empty() && sweep.is_some() && half.is_some();
    if factor.len() != symbolic.len_val() && !trimmed {
        return Err(bad("does not fit the body's split (factor length)"));
    }
    Ok((symbolic, factor, sweep, half))
}

/// The far map (rows `rows`, `g` interface components) and the contact columns (`m`
/// equations, a body of `nodes` nodes), checked against the split; the image must end there.
fn read_map_and_contact(
    r: &mut Reader<'_>,
    rows: &MapRows,
    g: usize,
    m: usize,
    nodes: usize,
) -> Result<(Vec<u16>, ContactColumns), ModelError> {
    let map: Vec<u16> = r.array()?;
    if map.len() != rows.map_far.len() * g {
        return Err(bad("does not fit the body's split (far map)"));
    }
    let col: Vec<u32> = r.array()?;
    let z: Vec<f32> = r.array()?;
    let prepared = col.iter().filter(|&&c| c != u32::MAX).count();
    if col.len() != nodes
        || col.iter().any(|&c| c != u32::MAX && c as usize >= prepared)
        || z.len() != 3 * m * prepared
    {
        return Err(bad("does not fit the body's split (contact columns)"));
    }
    if !r.bytes.is_empty() {
        return Err(bad("has trailing bytes"));
    }
    Ok((map, ContactColumns { col, z: z.into() }))
}

/// The row-major `g x g` symmetric matrix of the packed upper triangle `packed`
/// ([`packed_row_start`]), in double precision.
pub(super) fn unpack_symmetric(packed: &[f32], g: usize) -> Vec<f64> {
    let mut full = vec![0.0; g * g];
    for a in 0..g {
        let row = &packed[packed_row_start(a, g)..packed_row_start(a + 1, g)];
        for (k, &v) in row.iter().enumerate() {
            let b = a + k;
            full[a * g + b] = f64::from(v);
            full[b * g + a] = f64::from(v);
        }
    }
    full
}
