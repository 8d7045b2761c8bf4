//! `compact`: the client side of compact surface streams (`SURFACE_ENCODING_DELTA`).
//!
//! A [`CompactState`] keeps what a compact stream refers to, the topology (triangles and rest
//! positions, by version) and the reference keyframe (positions, by id), and turns every frame
//! into its full form ([`CompactState::expand`]): absolute `positions_m`, and `keyframe` with
//! triangles exactly when the topology changed. So the rest of the viewer (and the
//! [`crate::viewer::SurfaceState`] that renders) never sees deltas. Frames of FULL streams pass
//! unchanged. The relay of the web viewer ([`crate::web`]) keeps the same state to give late
//! browsers a keyframe.
//!
//! Neighbours: the encoding is `haptics_proto::delta`; the server side is
//! `haptic_server::stream`.

use std::sync::Arc;

use haptics_proto::delta::DeltaCodec;
use haptics_proto::v1::SurfaceFrame;

use crate::ClientError;

/// A topology of a compact stream.
#[derive(Debug, Clone)]
pub struct CompactTopology {
    /// `SurfaceFrame.topology_version`.
    pub version: u64,
    /// Triangles, three vertex indices each.
    pub triangles: Arc<Vec<u32>>,
    /// Rest positions, xyz, m.
    pub rest_positions_m: Arc<Vec<f32>>,
    /// Prediction order for decoding.
    pub codec: Arc<DeltaCodec>,
}

/// A reference keyframe of a compact stream.
#[derive(Debug, Clone)]
pub struct CompactReference {
    /// `SurfaceFrame.keyframe_id`.
    pub id: u64,
    /// Reference positions, xyz, m.
    pub positions_m: Arc<Vec<f32>>,
}

/// What a compact stream's frames refer to (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct CompactState {
    /// The last topology received.
    pub topology: Option<CompactTopology>,
    /// The last reference keyframe received.
    pub reference: Option<CompactReference>,
    /// How the last reference was chained from the one before: `(base id, reference_delta)`
    /// (a relay forwards it to clients that have the base).
    pub chain: Option<(u64, prost::bytes::Bytes)>,
}

impl CompactState {
    /// An empty state (expects a keyframe first).
    pub fn new() -> Self {
        Self::default()
    }

    /// True for frames of a compact stream (a quantum is set).
    pub fn is_compact(f: &SurfaceFrame) -> bool {
        f.quantum_m > 0.0
    }

    /// Records the topology and reference a compact frame carries, without decoding its
    /// positions (what a relay needs). Returns whether the frame brought a new topology.
    ///
    /// # Errors
    /// [`ClientError::BadFrame`] for a keyframe whose triangles do not fit its positions, or a
    /// reference keyframe of a topology that was never received; the state is unchanged.
    pub fn track(&mut self, f: &SurfaceFrame) -> Result<bool, ClientError> {
        let bad = |reason: String| ClientError::BadFrame {
            frame: f.frame,
            reason,
        };
        if !Self::is_compact(f) || !f.keyframe {
            return Ok(false);
        }
        if f.positions_m.is_empty() && f.base_keyframe_id != 0 {
            return self.chain_reference(f);
        }
        let n = f.positions_m.len() / 3;
        if f.positions_m.len() != 3 * n || f.positions_m.iter().any(|v| !v.is_finite()) {
            return Err(bad("keyframe positions are not finite xyz triples".into()));
        }
        let mut new_topology = false;
        let topology = if f.triangles.is_empty() {
            match &self.topology {
                Some(t) if t.version == f.topology_version && t.codec.vertex_count() == n => {
                    t.clone()
                }
                _ => {
                    return Err(bad(format!(
                        "keyframe without triangles for topology {} that was never received",
                        f.topology_version
                    )));
                }
            }
        } else {
            let codec = DeltaCodec::new(n, &f.triangles).map_err(|e| bad(e.to_string()))?;
            let rest = if f.rest_positions_m.len() == f.positions_m.len() {
                f.rest_positions_m.clone()
            } else {
                f.positions_m.clone()
            };
            new_topology = true;
            CompactTopology {
                version: f.topology_version,
                triangles: Arc::new(f.triangles.clone()),
                rest_positions_m: Arc::new(rest),
                codec: Arc::new(codec),
            }
        };
        self.topology = Some(topology);
        self.reference = Some(CompactReference {
            id: f.keyframe_id,
            positions_m: Arc::new(f.positions_m.clone()),
        });
        self.chain = None;
        Ok(new_topology)
    }

    /// A chained keyframe: the new reference is the base reference plus `reference_delta`.
    fn chain_reference(&mut self, f: &SurfaceFrame) -> Result<bool, ClientError> {
        let bad = |reason: String| ClientError::BadFrame {
            frame: f.frame,
            reason,
        };
        let (Some(topology), Some(base)) = (&self.topology, &self.reference) else {
            return Err(bad("chained keyframe before any keyframe".into()));
        };
        if base.id != f.base_keyframe_id || topology.version != f.topology_version {
            return Err(bad(format!(
                "keyframe {} chains from {} (topology {}), but the last keyframe was {}                  (topology {})",
                f.keyframe_id, f.base_keyframe_id, f.topology_version, base.id, topology.version
            )));
        }
        let mut positions = vec![0.0; base.positions_m.len()];
        topology
            .codec
            .decode(
                &base.positions_m,
                &f.reference_delta,
                f.quantum_m,
                &mut positions,
            )
            .map_err(|e| bad(e.to_string()))?;
        self.reference = Some(CompactReference {
            id: f.keyframe_id,
            positions_m: Arc::new(positions),
        });
        self.chain = Some((f.base_keyframe_id, f.reference_delta.clone()));
        Ok(false)
    }

    /// The full form of `f`: a FULL-stream frame passes unchanged; a compact frame gets
    /// absolute positions (reference + delta), and is a keyframe with triangles and rest
    /// positions exactly when it brought a new topology.
    ///
    /// # Errors
    /// [`ClientError::BadFrame`] when the frame refers to a reference keyframe or topology this
    /// state does not have, or its delta is malformed (the caller may ask for a keyframe with
    /// `SurfaceStream.RequestKeyframe`).
    pub fn expand(&mut self, mut f: SurfaceFrame) -> Result<SurfaceFrame, ClientError> {
        if !Self::is_compact(&f) {
            return Ok(f);
        }
        let bad = |frame: u64, reason: String| ClientError::BadFrame { frame, reason };
        let new_topology = self.track(&f)?;
        let quantum = f.quantum_m;
        if !f.keyframe && !f.positions_m.is_empty() && f.position_delta.is_empty() {
            // Absolute positions (the server could not express them against the reference).
            return Ok(f);
        }
        let (Some(topology), Some(reference)) = (&self.topology, &self.reference) else {
            return Err(bad(f.frame, "delta before the first keyframe".into()));
        };
        if reference.id != f.keyframe_id || topology.version != f.topology_version {
            return Err(bad(
                f.frame,
                format!(
                    "delta against keyframe {} (topology {}), but the last keyframe was {} \
                     (topology {})",
                    f.keyframe_id, f.topology_version, reference.id, topology.version
                ),
            ));
        }
        let mut positions = vec![0.0; reference.positions_m.len()];
        topology
            .codec
            .decode(
                &reference.positions_m,
                &f.position_delta,
                quantum,
                &mut positions,
            )
            .map_err(|e| bad(f.frame, e.to_string()))?;
        f.positions_m = positions;
        f.position_delta = Default::default();
        f.reference_delta = Default::default();
        f.base_keyframe_id = 0;
        f.keyframe = new_topology;
        if new_topology {
            f.triangles = topology.triangles.to_vec();
            f.rest_positions_m = topology.rest_positions_m.to_vec();
        } else {
            f.triangles.clear();
            f.rest_positions_m.clear();
        }
        Ok(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(id: u64, version: u64, triangles: bool) -> SurfaceFrame {
        SurfaceFrame {
            keyframe: true,
            positions_m: vec![0., 0., 0., 0.01, 0., 0., 0., 0.01, 0.],
            triangles: if triangles { vec![0, 1, 2] } else { vec![] },
            quantum_m: 1e-6,
            keyframe_id: id,
            topology_version: version,
            ..Default::default()
        }
    }

    #[test]
    fn deltas_expand_against_their_keyframe_and_mismatches_are_errors() {
        let mut s = CompactState::new();
        let k = s.expand(key(1, 0, true)).unwrap();
        assert!(k.keyframe && k.triangles == [0, 1, 2]);
        let codec = DeltaCodec::new(3, &[0, 1, 2]).unwrap();
        let reference = key(1, 0, true).positions_m;
        let mut moved = reference.clone();
        moved[3] += 0.002;
        let mut payload = Vec::new();
        codec
            .encode(&reference, &moved, 1e-6, &mut payload)
            .unwrap();
        let delta = SurfaceFrame {
            position_delta: payload.clone().into(),
            quantum_m: 1e-6,
            keyframe_id: 1,
            ..Default::default()
        };
        let f = s.expand(delta.clone()).unwrap();
        assert!(!f.keyframe && f.triangles.is_empty());
        assert!((f.positions_m[3] - 0.012).abs() < 1e-6);
        // A refresh keyframe without triangles keeps the topology: not a keyframe downstream.
        let f = s.expand(key(2, 0, false)).unwrap();
        assert!(!f.keyframe);
        // The old reference is gone.
        assert!(s.expand(delta).is_err());
        // A refresh of an unknown topology is refused and leaves the state alone.
        assert!(s.expand(key(3, 9, false)).is_err());
        assert_eq!(s.reference.as_ref().unwrap().id, 2);
        // FULL frames pass unchanged.
        let full = SurfaceFrame {
            positions_m: vec![1.0; 9],
            ..Default::default()
        };
        assert_eq!(s.expand(full.clone()).unwrap(), full);
    }
}
