//! The compact position encoding of `SurfaceFrame.position_delta` (`SURFACE_ENCODING_DELTA`):
//! quantized displacements of the surface vertices from a reference keyframe.
//!
//! Layout, for `n` vertices with a reference `r` and current positions `p` (xyz interleaved,
//! f32, m) and a step `quantum_m`:
//!
//! 1. `q[v][c] = round((p[v][c] - r[v][c]) / quantum_m)`, an integer with `|q| < 2^26`
//!    (otherwise the frame is not representable and the sender sends a keyframe instead);
//! 2. the vertices are visited in breadth-first order over the keyframe's triangle edges
//!    (neighbours in ascending index order, each new tree rooted at the lowest unvisited
//!    index); each value is predicted by the same component of its BFS parent (roots: 0) and
//!    the residual `q - q_parent` is zigzag-mapped (`0, -1, 1, -2, ...` -> `0, 1, 2, 3, ...`);
//! 3. the residuals, component-major (all x, then all y, then all z, each in BFS order), are
//!    bit-packed in blocks of 16: a 5-bit width `w` (0..=28), then the block's values in `w`
//!    bits each, least significant bit first in a little-endian bit stream; the last byte is
//!    padded with zeros.
//!
//! An empty payload means "no displacement from the reference". The decoder checks the length
//! exactly and every width, so a malformed payload is an error, never a panic. The web viewer
//! (`client-viewer/web/app.js`) implements the same decoder.
//!
//! Why: the displacement field is smooth, so a neighbour predicts a vertex well (on the default
//! LV under a 3.7 mm press, 1 um steps: 2.3 kB per frame instead of 3.1 kB unpredicted varints
//! and 8.3 kB of floats); blocks of 16 let far, still regions cost 5 bits per 16 values.
//! Measurements: `docs/benchmarks.md` (compact surface streams).

use std::collections::VecDeque;

/// Default quantum (step) of the deltas, m (1 um).
pub const DEFAULT_QUANTUM_M: f64 = 1e-6;
/// Smallest accepted quantum, m (f32 positions of a 0.1 m body resolve about 7 nm).
pub const MIN_QUANTUM_M: f64 = 1e-8;
/// Largest accepted quantum, m.
pub const MAX_QUANTUM_M: f64 = 1e-3;
/// Values per bit-packed block.
pub const BLOCK: usize = 16;
/// Largest quantized displacement magnitude, in quanta (exclusive).
pub const MAX_QUANTA: i64 = 1 << 26;
const MAX_WIDTH: u32 = 28;

/// Why a delta could not be encoded or decoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeltaError {
    /// A triangle names a vertex outside `0..vertex_count`, or the triangle list is not a
    /// multiple of 3.
    #[error("bad topology: {0}")]
    Topology(String),
    /// Slice lengths do not match `3 * vertex_count`.
    #[error("expected {expected} values, got {got}")]
    Length {
        /// `3 * vertex_count`.
        expected: usize,
        /// What was given.
        got: usize,
    },
    /// The quantum is not finite or outside [`MIN_QUANTUM_M`]..=[`MAX_QUANTUM_M`].
    #[error("quantum {0} m is outside 1e-8 ..= 1e-3 m")]
    Quantum(f64),
    /// A position is not finite or a displacement needs more than 2^26 quanta (send a keyframe).
    #[error("displacement not representable at this quantum")]
    NotRepresentable,
    /// The payload is malformed (too short, too long, or a bad block width).
    #[error("malformed delta payload: {0}")]
    Malformed(&'static str),
}

/// Checks a quantum, m.
///
/// # Errors
/// [`DeltaError::Quantum`] when not finite or out of range.
pub fn check_quantum(quantum_m: f64) -> Result<f64, DeltaError> {
    if quantum_m.is_finite() && (MIN_QUANTUM_M..=MAX_QUANTUM_M).contains(&quantum_m) {
        Ok(quantum_m)
    } else {
        Err(DeltaError::Quantum(quantum_m))
    }
}

/// The prediction order of one surface topology (built once per keyframe topology, reused
/// for every frame).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeltaCodec {
    /// Vertices in breadth-first order.
    order: Vec<u32>,
    /// BFS parent of each vertex, `u32::MAX` for roots.
    parent: Vec<u32>,
}

impl DeltaCodec {
    /// Builds the prediction order for `vertex_count` vertices and `triangles` (three vertex
    /// indices each).
    ///
    /// # Errors
    /// [`DeltaError::Topology`] when a triangle index is out of range or the list length is
    /// not a multiple of 3.
    pub fn new(vertex_count: usize, triangles: &[u32]) -> Result<Self, DeltaError> {
        if !triangles.len().is_multiple_of(3) {
            return Err(DeltaError::Topology(format!(
                "{} triangle indices is not a multiple of 3",
                triangles.len()
            )));
        }
        if let Some(&i) = triangles.iter().find(|&&i| i as usize >= vertex_count) {
            return Err(DeltaError::Topology(format!(
                "triangle index {i} with {vertex_count} vertices"
            )));
        }
        let mut adjacency: Vec<Vec<u32>> = vec![Vec::new(); vertex_count];
        for t in triangles.chunks_exact(3) {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                adjacency[a as usize].push(b);
                adjacency[b as usize].push(a);
            }
        }
        for a in &mut adjacency {
            a.sort_unstable();
            a.dedup();
        }
        let mut parent = vec![u32::MAX; vertex_count];
        let mut seen = vec![false; vertex_count];
        let mut order = Vec::with_capacity(vertex_count);
        let mut queue = VecDeque::new();
        for root in 0..vertex_count {
            if seen[root] {
                continue;
            }
            seen[root] = true;
            queue.push_back(root as u32);
            while let Some(v) = queue.pop_front() {
                order.push(v);
                for &w in &adjacency[v as usize] {
                    if !seen[w as usize] {
                        seen[w as usize] = true;
                        parent[w as usize] = v;
                        queue.push_back(w);
                    }
                }
            }
        }
        Ok(Self { order, parent })
    }

    /// Number of vertices.
    pub fn vertex_count(&self) -> usize {
        self.order.len()
    }

    /// Payload length in bytes for this topology (every non-empty payload has it).
    pub fn payload_len(&self) -> usize {
        let values = 3 * self.order.len();
        let blocks = values.div_ceil(BLOCK);
        // Upper bound used only for reservations: 5 + 28 * 16 bits per block.
        (blocks * (5 + MAX_WIDTH as usize * BLOCK)).div_ceil(8)
    }

    fn check_len(&self, got: usize) -> Result<(), DeltaError> {
        let expected = 3 * self.order.len();
        if got == expected {
            Ok(())
        } else {
            Err(DeltaError::Length { expected, got })
        }
    }

    /// Encodes `current - reference` (xyz interleaved, m) in steps of `quantum_m` into `out`
    /// (cleared first). Leaves `out` empty when every step is zero.
    ///
    /// # Errors
    /// [`DeltaError::Length`] for slices that are not `3 * vertex_count` long;
    /// [`DeltaError::Quantum`]; [`DeltaError::NotRepresentable`] for non-finite positions or a
    /// displacement of `2^26` quanta or more (the caller sends a keyframe instead).
    pub fn encode(
        &self,
        reference: &[f32],
        current: &[f32],
        quantum_m: f64,
        out: &mut Vec<u8>,
    ) -> Result<(), DeltaError> {
        self.check_len(reference.len())?;
        self.check_len(current.len())?;
        let quantum_m = check_quantum(quantum_m)?;
        out.clear();
        let n = self.order.len();
        let mut q = vec![0i64; 3 * n];
        let mut any = false;
        for (i, (r, p)) in reference.iter().zip(current).enumerate() {
            let d = ((f64::from(*p) - f64::from(*r)) / quantum_m).round();
            if !d.is_finite() || d.abs() >= MAX_QUANTA as f64 {
                return Err(DeltaError::NotRepresentable);
            }
            q[i] = d as i64;
            any |= q[i] != 0;
        }
        if !any {
            return Ok(());
        }
        let mut bits = BitWriter::new(out);
        let mut block = [0u32; BLOCK];
        let mut len = 0;
        for c in 0..3 {
            for &v in &self.order {
                let x = q[3 * v as usize + c];
                let p = self.parent[v as usize];
                let pred = if p == u32::MAX {
                    0
                } else {
                    q[3 * p as usize + c]
                };
                block[len] = zigzag(x - pred);
                len += 1;
                if len == BLOCK {
                    bits.block(&block[..len]);
                    len = 0;
                }
            }
        }
        if len > 0 {
            bits.block(&block[..len]);
        }
        bits.finish();
        Ok(())
    }

    /// Decodes `payload` against `reference` (xyz interleaved, m) into `out`:
    /// `out = reference + q * quantum_m`, rounded to f32. An empty payload copies `reference`.
    ///
    /// # Errors
    /// [`DeltaError::Length`] for slices that are not `3 * vertex_count` long;
    /// [`DeltaError::Quantum`]; [`DeltaError::Malformed`] for a payload that is too short, too
    /// long or has a block width above 28.
    pub fn decode(
        &self,
        reference: &[f32],
        payload: &[u8],
        quantum_m: f64,
        out: &mut [f32],
    ) -> Result<(), DeltaError> {
        self.check_len(reference.len())?;
        self.check_len(out.len())?;
        let quantum_m = check_quantum(quantum_m)?;
        if payload.is_empty() {
            out.copy_from_slice(reference);
            return Ok(());
        }
        let n = self.order.len();
        let mut q = vec![0i64; 3 * n];
        let mut bits = BitReader::new(payload);
        let mut remaining_in_block = 0usize;
        let mut width = 0u32;
        for c in 0..3 {
            for &v in &self.order {
                if remaining_in_block == 0 {
                    width = bits.read(5).ok_or(DeltaError::Malformed("truncated"))? as u32;
                    if width > MAX_WIDTH {
                        return Err(DeltaError::Malformed("block width above 28"));
                    }
                    remaining_in_block = BLOCK;
                }
                let u = bits.read(width).ok_or(DeltaError::Malformed("truncated"))? as u32;
                remaining_in_block -= 1;
                let p = self.parent[v as usize];
                let pred = if p == u32::MAX {
                    0
                } else {
                    q[3 * p as usize + c]
                };
                q[3 * v as usize + c] = pred + unzigzag(u);
            }
        }
        if bits.bytes_used() != payload.len() {
            return Err(DeltaError::Malformed("trailing bytes"));
        }
        for ((o, r), d) in out.iter_mut().zip(reference).zip(&q) {
            *o = (f64::from(*r) + *d as f64 * quantum_m) as f32;
        }
        Ok(())
    }
}

fn zigzag(x: i64) -> u32 {
    ((x << 1) ^ (x >> 63)) as u32
}

fn unzigzag(u: u32) -> i64 {
    (i64::from(u) >> 1) ^ -(i64::from(u) & 1)
}

struct BitWriter<'a> {
    out: &'a mut Vec<u8>,
    acc: u64,
    n: u32,
}

impl<'a> BitWriter<'a> {
    fn new(out: &'a mut Vec<u8>) -> Self {
        Self { out, acc: 0, n: 0 }
    }

    fn put(&mut self, value: u32, width: u32) {
        self.acc |= u64::from(value) << self.n;
        self.n += width;
        while self.n >= 8 {
            self.out.push(self.acc as u8);
            self.acc >>= 8;
            self.n -= 8;
        }
    }

    fn block(&mut self, values: &[u32]) {
        let max = values.iter().copied().max().unwrap_or(0);
        let width = 32 - max.leading_zeros();
        self.put(width, 5);
        if width > 0 {
            for &v in values {
                self.put(v, width);
            }
        }
    }

    fn finish(mut self) {
        if self.n > 0 {
            self.out.push(self.acc as u8);
            self.acc = 0;
            self.n = 0;
        }
    }
}

struct BitReader<'a> {
    data: &'a [u8],
    byte: usize,
    acc: u64,
    n: u32,
}

impl<'a> BitReader<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self {
            data,
            byte: 0,
            acc: 0,
            n: 0,
        }
    }

    fn read(&mut self, width: u32) -> Option<u64> {
        while self.n < width {
            let b = *self.data.get(self.byte)?;
            self.acc |= u64::from(b) << self.n;
            self.byte += 1;
            self.n += 8;
        }
        let v = self.acc & ((1u64 << width) - 1);
        self.acc >>= width;
        self.n -= width;
        Some(v)
    }

    fn bytes_used(&self) -> usize {
        self.byte
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 5 x 5 grid of vertices (25), two triangles per cell.
    fn grid() -> (Vec<f32>, Vec<u32>) {
        let mut p = Vec::new();
        for j in 0..5 {
            for i in 0..5 {
                p.extend([i as f32 * 0.002, j as f32 * 0.002, 0.01]);
            }
        }
        let mut t = Vec::new();
        for j in 0..4u32 {
            for i in 0..4u32 {
                let a = j * 5 + i;
                t.extend([a, a + 1, a + 6, a, a + 6, a + 5]);
            }
        }
        (p, t)
    }

    #[test]
    fn round_trip_is_within_half_a_quantum() {
        let (rest, tris) = grid();
        let codec = DeltaCodec::new(25, &tris).unwrap();
        let mut cur = rest.clone();
        for (i, v) in cur.iter_mut().enumerate() {
            *v += (i as f32 * 0.37).sin() * 3e-3;
        }
        for quantum in [1e-8, 1e-6, 1e-5, 1e-3] {
            let mut buf = Vec::new();
            codec.encode(&rest, &cur, quantum, &mut buf).unwrap();
            let mut out = vec![0.0; 75];
            codec.decode(&rest, &buf, quantum, &mut out).unwrap();
            for (a, b) in out.iter().zip(&cur) {
                let tol = quantum / 2.0 + 2.0 * f64::from(f32::EPSILON) * 0.02;
                assert!(f64::from((a - b).abs()) <= tol, "{a} {b} at {quantum}");
            }
        }
    }

    #[test]
    fn no_displacement_is_an_empty_payload_and_smooth_fields_are_small() {
        let (rest, tris) = grid();
        let codec = DeltaCodec::new(25, &tris).unwrap();
        let mut buf = vec![1, 2, 3];
        codec.encode(&rest, &rest, 1e-6, &mut buf).unwrap();
        assert!(buf.is_empty());
        let mut out = vec![0.0; 75];
        codec.decode(&rest, &[], 1e-6, &mut out).unwrap();
        assert_eq!(out, rest);
        // A rigid shift of 1 mm: the root carries it, every residual after it is zero.
        let shifted: Vec<f32> = rest.iter().map(|v| v + 1e-3).collect();
        codec.encode(&rest, &shifted, 1e-6, &mut buf).unwrap();
        // 75 values in 5 blocks of 5-bit widths; the three blocks holding a root's 1000 quanta
        // (zigzag 2000) pack 16 values of 11 bits, the other two are empty: 553 bits.
        assert_eq!(buf.len(), 70);
        codec.decode(&rest, &buf, 1e-6, &mut out).unwrap();
        assert!(out.iter().zip(&shifted).all(|(a, b)| (a - b).abs() < 1e-6));
    }

    #[test]
    fn bfs_order_is_deterministic_and_covers_isolated_vertices() {
        let codec = DeltaCodec::new(5, &[0, 2, 3]).unwrap();
        assert_eq!(codec.order, vec![0, 2, 3, 1, 4]);
        assert_eq!(codec.parent, vec![u32::MAX, u32::MAX, 0, 0, u32::MAX]);
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let (rest, tris) = grid();
        assert!(matches!(
            DeltaCodec::new(24, &tris),
            Err(DeltaError::Topology(_))
        ));
        assert!(DeltaCodec::new(25, &tris[..4]).is_err());
        let codec = DeltaCodec::new(25, &tris).unwrap();
        let mut buf = Vec::new();
        let mut far = rest.clone();
        far[7] = 100.0;
        assert_eq!(
            codec.encode(&rest, &far, 1e-6, &mut buf),
            Err(DeltaError::NotRepresentable)
        );
        far[7] = f32::NAN;
        assert_eq!(
            codec.encode(&rest, &far, 1e-6, &mut buf),
            Err(DeltaError::NotRepresentable)
        );
        assert!(matches!(
            codec.encode(&rest, &rest[..3], 1e-6, &mut buf),
            Err(DeltaError::Length { .. })
        ));
        for q in [0.0, -1e-6, f64::NAN, 1.0] {
            assert!(matches!(
                codec.encode(&rest, &rest, q, &mut buf),
                Err(DeltaError::Quantum(_))
            ));
        }
        let mut cur = rest.clone();
        cur[0] += 1e-4;
        codec.encode(&rest, &cur, 1e-6, &mut buf).unwrap();
        let mut out = vec![0.0; 75];
        let mut long = buf.clone();
        long.push(0);
        assert!(codec.decode(&rest, &long, 1e-6, &mut out).is_err());
        assert!(
            codec
                .decode(&rest, &buf[..buf.len() - 1], 1e-6, &mut out)
                .is_err()
        );
        // Every byte string up to 3 bytes, and corrupted payloads: errors or values, no panic.
        for a in 0..=255u8 {
            let _ = codec.decode(&rest, &[a], 1e-6, &mut out);
            let _ = codec.decode(&rest, &[a, 0xff, a], 1e-6, &mut out);
        }
        for i in 0..buf.len() {
            let mut bad = buf.clone();
            bad[i] ^= 0xa5;
            let _ = codec.decode(&rest, &bad, 1e-6, &mut out);
        }
        assert!(codec.decode(&rest, &[0xff; 64], 1e-6, &mut out).is_err());
    }
}
