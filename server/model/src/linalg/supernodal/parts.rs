//! A [`HalfFactor`] as plain arrays and back (the region cache's images,
//! `integrate::condensed::image`), and reading one through to bring it back into the caches.

use super::{HalfFactor, SupernodalSolve, panels, supernode};

/// The arrays of a [`HalfFactor`] (scale, inverted diagonal, supernode starts, panel
/// triangles, half-precision bits), for the region cache's files
/// ([`HalfFactor::to_parts`], [`SupernodalSolve::half_factor_from_parts`]).
pub type HalfFactorParts = (Vec<f32>, Vec<f32>, Vec<[u32; 2]>, Vec<f32>, Vec<u16>);

impl HalfFactor {
    /// Its arrays, as [`SupernodalSolve::half_factor_from_parts`] takes them back.
    pub fn to_parts(&self) -> HalfFactorParts {
        (
            self.scale.clone(),
            self.inv_diag.clone(),
            self.node_start.clone(),
            self.triangles.clone(),
            self.values.clone(),
        )
    }

    /// Reads every array once (a sum of their bits, for [`std::hint::black_box`]): brings a
    /// factor that has not been read for a while back into the caches, and its pages into
    /// memory, on the thread that calls it rather than on the first tick that sweeps it.
    pub fn touch(&self) -> u64 {
        touch_words(&self.values)
            .wrapping_add(touch_words(&self.scale))
            .wrapping_add(touch_words(&self.inv_diag))
            .wrapping_add(touch_words(&self.triangles))
    }
}

/// A sum of `values`' bits, read a cache line (64 bytes) at a time.
pub fn touch_words<T: bytemuck::Pod>(values: &[T]) -> u64 {
    bytemuck::cast_slice::<T, u8>(values)
        .iter()
        .step_by(64)
        .fold(0u64, |a, &b| a.wrapping_add(u64::from(b)))
}

impl SupernodalSolve {
    /// The half-precision factor with the arrays `parts` ([`HalfFactor::to_parts`] of a
    /// factor of this structure), or `None` when their lengths or supernode starts are not
    /// the ones [`Self::half_factor`] makes on this structure: a factor read back from a file
    /// cannot make a sweep read out of bounds.
    pub fn half_factor_from_parts(&self, parts: HalfFactorParts) -> Option<HalfFactor> {
        let (scale, inv_diag, node_start, triangles, values) = parts;
        let n = self.x.len();
        if scale.len() != n || inv_diag.len() != n || node_start.len() != self.nodes.len() + 1 {
            return None;
        }
        let (mut half, mut tri) = (0usize, 0usize);
        for (&node, start) in self.nodes.iter().zip(&node_start) {
            if start[0] as usize != half || start[1] as usize != tri {
                return None;
            }
            let (_, nc, _, pattern) = supernode(node, &self.rows);
            for p in panels(nc, nc + pattern.len()) {
                half += p.values_len;
                tri += p.triangle_len;
            }
        }
        let last = node_start[self.nodes.len()];
        (last[0] as usize == half
            && last[1] as usize == tri
            && values.len() == half
            && triangles.len() == tri)
            .then_some(HalfFactor {
                scale,
                inv_diag,
                node_start,
                triangles,
                values,
            })
    }
}
