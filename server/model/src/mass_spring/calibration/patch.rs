//! The local calibration problem of one contact node (module documentation of [`super`]): the
//! patch of the surface around it, coarse and subdivided, pressed at the node.

use super::*;

/// The local calibration problem of one contact node: a patch of the surface around it, coarse
/// and subdivided, pressed at the node (module documentation).
#[derive(Debug, Clone)]
pub struct LocalPatch {
    shape: ContactShape,
    centre: u32,
    element_size_m: f64,
    contact_point: DVec3,
    normal: DVec3,
    coarse: Network,
    coarse_triangles: Vec<[u32; 3]>,
    fine: Network,
    fine_triangles: Vec<[u32; 3]>,
    /// Per fine node: in the subdivided area (home spring `K'_h`).
    fine_area_node: Vec<bool>,
    /// Per fine spring: in the subdivided area (`K'_m`).
    fine_area_spring: Vec<bool>,
    /// Per coarse node and per fine slot: contact position minus rest position at rest, m
    /// ([`crate::mass_spring::contact_rest`]).
    coarse_offset: Vec<DVec3>,
    fine_offset: Vec<DVec3>,
    type1: usize,
    type2: usize,
    kh: f64,
    km: f64,
}

/// The margin [`LocalPatch::new`] keeps around the subdivided rings of node `centre`:
/// [`PATCH_EXTRA_RINGS`], and for the probe as many rings again as its patch reaches (`2 r`).
pub fn default_margin(surface: &SpringSurface, centre: u32, shape: ContactShape) -> u32 {
    match shape {
        ContactShape::Point => PATCH_EXTRA_RINGS,
        ContactShape::Probe(p) => {
            let l = surface.element_size_m(centre);
            PATCH_EXTRA_RINGS + (2.0 * p.radius_m / l).ceil() as u32
        }
    }
}

/// The contact positions at rest the probe of `shape` sees on `surface`
/// ([`contact_rest_positions`]; `None` for the point contact, which presses the node itself).
pub fn surface_contact_rest(surface: &SpringSurface, shape: ContactShape) -> Option<ContactRest> {
    match shape {
        ContactShape::Point => None,
        ContactShape::Probe(p) => Some(contact_rest_positions(surface, p)),
    }
}

impl LocalPatch {
    /// The patch of `surface` around node `centre` for subdividing `rings` rings with
    /// `vertex_rule`, coarse constants `K_h = kh`, `K_m = km` (N/m), pressed with `shape`.
    ///
    /// # Errors
    /// [`ModelError::InvalidInput`] for a fixed centre or `rings == 0`; the errors of
    /// [`SpringSurface`] for a patch that is not a valid surface.
    pub fn new(
        surface: &SpringSurface,
        centre: u32,
        rings: u32,
        vertex_rule: VertexRule,
        shape: ContactShape,
        constants: (f64, f64),
    ) -> Result<Self, ModelError> {
        let margin = default_margin(surface, centre, shape);
        Self::with_margin(
            surface,
            centre,
            rings,
            margin,
            vertex_rule,
            shape,
            constants,
        )
    }

    /// [`LocalPatch::new`] with `margin` rings beyond the subdivided ones (the outermost held
    /// at rest), for the patch-size convergence check.
    ///
    /// # Errors
    /// As [`LocalPatch::new`].
    pub fn with_margin(
        surface: &SpringSurface,
        centre: u32,
        rings: u32,
        margin: u32,
        vertex_rule: VertexRule,
        shape: ContactShape,
        constants: (f64, f64),
    ) -> Result<Self, ModelError> {
        let contact = surface_contact_rest(surface, shape);
        Self::with_contact(
            surface,
            centre,
            rings,
            margin,
            vertex_rule,
            shape,
            constants,
            contact.as_ref(),
        )
    }

    /// [`LocalPatch::with_margin`] with the whole surface's contact positions at rest computed
    /// beforehand (`contact`, [`crate::mass_spring::contact_rest::contact_rest_positions`] for the probe of
    /// `shape`; `None` for a point contact): the calibration of every node computes them once.
    ///
    /// # Errors
    /// As [`LocalPatch::new`].
    #[allow(clippy::too_many_arguments)]
    pub fn with_contact(
        surface: &SpringSurface,
        centre: u32,
        rings: u32,
        margin: u32,
        vertex_rule: VertexRule,
        shape: ContactShape,
        (kh, km): (f64, f64),
        contact: Option<&ContactRest>,
    ) -> Result<Self, ModelError> {
        if rings == 0 || margin == 0 || surface.is_fixed(centre) {
            return Err(ModelError::InvalidInput(format!(
                "node {centre} cannot be calibrated (fixed, or no ring to subdivide or margin)"
            )));
        }
        let (ring, patch) = cut_patch(surface, centre, rings + margin)?;
        let c = 0u32; // the ring starts with the centre
        let nc = patch.node_count();
        let coarse = coarse_network(&patch, kh, km);
        // Subdivided network over slots (coarse nodes, then one per edge), as at run time.
        let mut refinement = Refinement::new(&patch);
        refinement.begin();
        refinement.request_ring(&patch, c, rings, 0);
        refinement.finish(&patch);
        let fine_mesh = refinement.mesh(&patch);
        let ns = nc + patch.edge_count();
        let fine_rest = fine_rest_positions(&patch, &refinement, vertex_rule);
        let mut fine_fixed: Vec<bool> = coarse.fixed.clone();
        fine_fixed.resize(ns, true);
        for &e in refinement.active_edges() {
            let [a, b] = patch.edges()[e as usize];
            fine_fixed[nc + e as usize] = patch.is_fixed(a) && patch.is_fixed(b);
        }
        let fine_area_node: Vec<bool> = (0..ns as u32)
            .map(|s| refinement.node_owner(s) != NO_OWNER)
            .collect();
        let mut fine_area_spring = Vec::new();
        let springs: Vec<Spring> = fine_mesh
            .springs
            .iter()
            .map(|s| {
                fine_area_spring.push(s.owner != NO_OWNER);
                Spring {
                    i: s.i,
                    j: s.j,
                    rest_length_m: (fine_rest[s.j as usize] - fine_rest[s.i as usize]).length(),
                    stiffness_n_per_m: km,
                }
            })
            .collect();
        let (coarse_offset, fine_offset) = match contact {
            Some(cr) => contact_offsets(surface, &patch, &ring, cr, &fine_rest),
            None => (vec![DVec3::ZERO; nc], vec![DVec3::ZERO; ns]),
        };
        // Depth zero is the sphere touching the node (on the surface the nodes sample; the
        // offsets put the probe's plane through it).
        let contact_point = surface.rest()[centre as usize];
        let fine = Network {
            home_n_per_m: (0..ns)
                .map(|s| if s < nc || fine_area_node[s] { kh } else { 0.0 })
                .collect(),
            rest: fine_rest,
            fixed: fine_fixed,
            springs,
        };
        Ok(Self {
            shape,
            centre: c,
            element_size_m: surface.element_size_m(centre),
            contact_point,
            normal: surface.rest_normal(centre),
            coarse,
            coarse_triangles: patch.triangles().to_vec(),
            fine,
            fine_triangles: fine_mesh.triangles,
            fine_area_node,
            fine_area_spring,
            coarse_offset,
            fine_offset,
            type1: refinement.type1_count(),
            type2: refinement.type2_count(),
            kh,
            km,
        })
    }

    /// Element size L at the contact node, m.
    pub fn element_size_m(&self) -> f64 {
        self.element_size_m
    }

    /// N and N' of eq. 3 and 5: nodes of the subdivided area before and after subdivision.
    pub fn area_node_counts(&self) -> (usize, usize) {
        (self.type1, self.type1 + self.type2)
    }

    /// Rest positions of the coarse patch (the initial guess of [`LocalPatch::coarse_press`]).
    pub fn coarse_rest(&self) -> Vec<DVec3> {
        self.coarse.rest.clone()
    }

    /// Rest positions of the subdivided patch (the initial guess of [`LocalPatch::fine_press`]).
    pub fn fine_rest(&self) -> Vec<DVec3> {
        self.fine.rest.clone()
    }

    /// The contact force (N) on `net` (triangles `tris`) at depth `depth_m` (m): for
    /// [`ContactShape::Point`] the contact node's displacement along its rest normal; for
    /// [`ContactShape::Probe`] the travel of the probe centre along `-n` from `r` above the
    /// contact node at rest, the force then being the probe's (its patch, weights and normal
    /// at the deformed positions, the coupling in series), found by a fixed point on the
    /// probe's patch around Newton solves of [`press`]. `x` is the solution (warm start).
    fn force(
        &self,
        (net, tris, offset): (&Network, &[[u32; 3]], &[DVec3]),
        depth_m: f64,
        coupling: bool,
        x: &mut [DVec3],
    ) -> Result<f64, ModelError> {
        let guess = self.kh * depth_m;
        let p = match self.shape {
            ContactShape::Point => {
                let load = ContactLoad {
                    nodes: vec![(self.centre, 1.0)],
                    normal: self.normal,
                    compliance_m_per_n: 0.0,
                };
                return Ok(press(net, &load, depth_m, x, guess)?.force_n);
            }
            ContactShape::Probe(p) => p,
        };
        let device = self.contact_point + self.normal * (p.radius_m - depth_m);
        let contact_rest: Vec<DVec3> = net.rest.iter().zip(offset).map(|(r, o)| *r + *o).collect();
        let mut cx = contact_rest.clone();
        let mut probe = Probe::new(p, tris.to_vec(), &contact_rest);
        let mut load = ContactLoad {
            nodes: Vec::new(),
            normal: self.normal,
            compliance_m_per_n: if coupling {
                1.0 / p.coupling_stiffness_n_per_m
            } else {
                0.0
            },
        };
        let mut f_prev = f64::NAN;
        let mut x_prev = x.to_vec();
        // The patch follows the surface it moved: the solve is a fixed point (freeze the patch
        // at x, solve). Plain iteration alternates (contraction about -0.8 on the hemisphere);
        // half steps damp it to about 0.1, and the step halves again whenever the change grows
        // (deep presses, where nodes enter and leave the patch).
        let (mut omega, mut change_prev) = (0.5, f64::INFINITY);
        for outer in 0..300 {
            for ((c, xi), o) in cx.iter_mut().zip(x.iter()).zip(offset) {
                *c = *xi + *o;
            }
            let st = probe.update(&cx, device, DVec3::ZERO);
            if st.in_contact {
                let (nodes, w) = probe.patch();
                load.nodes.clear();
                load.nodes
                    .extend(nodes.iter().copied().zip(w.iter().copied()));
                load.normal = st.normal;
            } else if load.nodes.is_empty() {
                return Ok(0.0); // the probe does not reach the surface
            }
            let c_rest: DVec3 = load
                .nodes
                .iter()
                .map(|&(i, w)| contact_rest[i as usize] * w)
                .sum();
            let depth_eff = p.radius_m - (device - c_rest).dot(load.normal);
            if depth_eff <= 0.0 {
                x.copy_from_slice(&net.rest);
                return Ok(0.0);
            }
            let f = press(net, &load, depth_eff, x, guess)?.force_n;
            let change = (f - f_prev).abs();
            if change <= 1e-7 * f.abs().max(1e-9) {
                return Ok(f);
            }
            if change > change_prev {
                omega = (omega * 0.5_f64).max(0.02);
            }
            change_prev = change;
            f_prev = f;
            if outer > 0 {
                for (xi, pi) in x.iter_mut().zip(&x_prev) {
                    *xi = *pi + (*xi - *pi) * omega;
                }
            }
            x_prev.copy_from_slice(x);
        }
        if change_prev <= 1e-4 * f_prev.abs() {
            return Ok(f_prev);
        }
        Err(ModelError::NoConvergence(format!(
            "the probe's patch did not settle at depth {depth_m:.3e} m (last change {change_prev:.2e} N)"
        )))
    }

    /// The coarse contact force at depth `depth_m` (m; see [`ContactShape`]), N; `x` (m) is
    /// the solution, updated from its value (warm start).
    ///
    /// # Errors
    /// As [`press`].
    pub fn coarse_press(&self, depth_m: f64, x: &mut [DVec3]) -> Result<f64, ModelError> {
        self.force(
            (&self.coarse, &self.coarse_triangles, &self.coarse_offset),
            depth_m,
            true,
            x,
        )
    }

    /// The coarse contact force at the probe sphere's depth `depth_m` (m; the plane's travel,
    /// without the virtual coupling in series: the sphere depth of [`crate::press`]) for the
    /// probe, and at the node's displacement for a point contact, N; `x` as in
    /// [`LocalPatch::coarse_press`].
    ///
    /// # Errors
    /// As [`press`].
    pub fn coarse_press_sphere_depth(
        &self,
        depth_m: f64,
        x: &mut [DVec3],
    ) -> Result<f64, ModelError> {
        self.force(
            (&self.coarse, &self.coarse_triangles, &self.coarse_offset),
            depth_m,
            false,
            x,
        )
    }

    /// The subdivided contact force at depth `depth_m` with `K'_h = kh_area` and `K'_m =
    /// km_area` (N/m) in the subdivided area: `(force N, displacement of the contact node m)`.
    ///
    /// # Errors
    /// As [`press`].
    pub fn fine_press(
        &mut self,
        area: (f64, f64),
        depth_m: f64,
        x: &mut [DVec3],
    ) -> Result<(f64, f64), ModelError> {
        self.fine_press_with(area, depth_m, true, x)
    }

    /// [`LocalPatch::fine_press`] at the probe sphere's depth `depth_m` (without the coupling in
    /// series, as [`LocalPatch::coarse_press_sphere_depth`]).
    ///
    /// # Errors
    /// As [`press`].
    pub fn fine_press_sphere_depth(
        &mut self,
        area: (f64, f64),
        depth_m: f64,
        x: &mut [DVec3],
    ) -> Result<(f64, f64), ModelError> {
        self.fine_press_with(area, depth_m, false, x)
    }

    fn fine_press_with(
        &mut self,
        (kh_area, km_area): (f64, f64),
        depth_m: f64,
        coupling: bool,
        x: &mut [DVec3],
    ) -> Result<(f64, f64), ModelError> {
        let nc = self.coarse.node_count();
        for (k, &area) in self.fine_area_node.iter().enumerate() {
            if area {
                self.fine.home_n_per_m[k] = kh_area;
            } else if k < nc {
                self.fine.home_n_per_m[k] = self.kh;
            }
        }
        for (s, &area) in self.fine.springs.iter_mut().zip(&self.fine_area_spring) {
            s.stiffness_n_per_m = if area { km_area } else { self.km };
        }
        let f = self.force(
            (&self.fine, &self.fine_triangles, &self.fine_offset),
            depth_m,
            coupling,
            x,
        )?;
        let c = self.centre as usize;
        Ok((f, (x[c] - self.fine.rest[c]).length()))
    }

    /// Finds the factor `s` with `F'(constants(s), depth) = target_n` (eq. 4) by secant
    /// iterations on `log s` (bracketed, to a relative force error of 1e-5), starting at
    /// `s_guess`: `Some((s, contact node displacement m))`, or `None` when no `s` in
    /// `[1e-3, 1e3] s_guess` reaches the target (e.g. the subdivided surface is not touched
    /// yet at that depth). `x` is the subdivided solution (warm start). `constants(s)` gives
    /// `(K'_h, K'_m)`; the force must not decrease with `s`.
    ///
    /// # Errors
    /// The errors of [`press`].
    pub fn match_force(
        &mut self,
        target_n: f64,
        depth_m: f64,
        constants: impl Fn(f64) -> (f64, f64),
        s_guess: f64,
        x: &mut [DVec3],
    ) -> Result<Option<(f64, f64)>, ModelError> {
        let mut eval = |s: f64, x: &mut [DVec3]| -> Result<(f64, f64), ModelError> {
            let (f, u) = self.fine_press(constants(s), depth_m, x)?;
            Ok((f - target_n, u))
        };
        let tol = 1e-5 * target_n.abs();
        let (mut s0, (mut h0, u0)) = (s_guess, eval(s_guess, x)?);
        if h0.abs() <= tol {
            return Ok(Some((s0, u0)));
        }
        let mut lo: Option<(f64, f64)> = None;
        let mut hi: Option<(f64, f64)> = None;
        let note = |s: f64, h: f64, lo: &mut Option<(f64, f64)>, hi: &mut Option<(f64, f64)>| {
            if h < 0.0 {
                *lo = Some((s, h));
            } else {
                *hi = Some((s, h));
            }
        };
        note(s0, h0, &mut lo, &mut hi);
        // Second point: the scale that would match if the force were proportional to s.
        let mut s1 = (s0 * (target_n / (target_n + h0))).clamp(s0 / 4.0, s0 * 4.0);
        if !(s1.is_finite() && s1 > 0.0) || s1 == s0 {
            s1 = if h0 < 0.0 { s0 * 1.5 } else { s0 / 1.5 };
        }
        for _ in 0..80 {
            let (h1, u1) = eval(s1, x)?;
            if h1.abs() <= tol {
                return Ok(Some((s1, u1)));
            }
            note(s1, h1, &mut lo, &mut hi);
            // Secant on log s, kept inside the bracket when there is one.
            let (l0, l1) = (s0.ln(), s1.ln());
            let mut next = if h1 != h0 {
                l1 - h1 * (l1 - l0) / (h1 - h0)
            } else {
                f64::NAN
            };
            match (lo, hi) {
                (Some((a, _)), Some((b, _))) => {
                    let (la, lb) = (a.ln(), b.ln());
                    if !(next > la.min(lb) && next < la.max(lb) && next.is_finite()) {
                        next = 0.5 * (la + lb);
                    }
                    if (la - lb).abs() < 1e-12 {
                        return Ok(Some((s1, u1)));
                    }
                }
                // Not bracketed yet: a secant through two points on the convex `F(log s)`
                // overshoots far when the start is far from the match (the table's first,
                // tiny-depth sample can give a factor 30 times the next one's), so a step
                // grows the factor by at most MAX_UNBRACKETED_STEP.
                (Some(_), None) => {
                    if !(next > l1 && next.is_finite()) {
                        next = l1 + 0.7;
                    }
                    next = next.min(l1 + MAX_UNBRACKETED_STEP);
                }
                (None, Some(_)) => {
                    if !(next < l1 && next.is_finite()) {
                        next = l1 - 0.7;
                    }
                    next = next.max(l1 - MAX_UNBRACKETED_STEP);
                }
                (None, None) => unreachable!("every evaluation is noted"),
            }
            (s0, h0) = (s1, h1);
            s1 = next.exp();
            if !(s1 > s_guess * 1e-3 && s1 < s_guess * 1e3) {
                return Ok(None);
            }
        }
        Ok(None)
    }
}

/// The coarse patch as a spring network: home springs `kh` at every node, mesh springs `km`
/// along every edge, N/m.
fn coarse_network(patch: &SpringSurface, kh: f64, km: f64) -> Network {
    let nc = patch.node_count();
    Network {
        rest: patch.rest().to_vec(),
        fixed: (0..nc as u32).map(|i| patch.is_fixed(i)).collect(),
        home_n_per_m: vec![kh; nc],
        springs: patch
            .edges()
            .iter()
            .map(|&[a, b]| Spring {
                i: a,
                j: b,
                rest_length_m: (patch.rest()[b as usize] - patch.rest()[a as usize]).length(),
                stiffness_n_per_m: km,
            })
            .collect(),
    }
}

/// Rest positions of the subdivided patch's slots (coarse nodes, then one per edge), as at
/// run time: the refined coarse nodes moved by Loop's vertex rule when `vertex_rule` says so,
/// every edge's new vertex by the edge rule.
fn fine_rest_positions(
    patch: &SpringSurface,
    refinement: &Refinement,
    vertex_rule: VertexRule,
) -> Vec<DVec3> {
    let nc = patch.node_count();
    let mut fine_rest = patch.rest().to_vec();
    let mut stencil = Vec::new();
    if vertex_rule == VertexRule::Loop {
        for i in 0..nc as u32 {
            if refinement.node_owner(i) != NO_OWNER && !patch.is_fixed(i) {
                vertex_stencil(patch, i, &mut stencil);
                fine_rest[i as usize] = apply(&stencil, patch.rest());
            }
        }
    }
    for e in 0..patch.edge_count() as u32 {
        fine_rest.push(apply(&edge_stencil(patch, e), patch.rest()));
    }
    fine_rest
}

/// The local problem's patch: the rings around `centre` up to `outer` (`ring`: the whole
/// surface's node and its ring distance, the centre first), the outermost ring and the
/// surface's fixed nodes fixed.
fn cut_patch(
    surface: &SpringSurface,
    centre: u32,
    outer: u32,
) -> Result<(Vec<(u32, u32)>, SpringSurface), ModelError> {
    let mut dist = vec![u32::MAX; surface.node_count()];
    let mut ring = Vec::new();
    surface.ring(centre, outer, &mut dist, &mut ring);
    let mut local = vec![NONE; surface.node_count()];
    for (k, &(i, _)) in ring.iter().enumerate() {
        local[i as usize] = k as u32;
    }
    let rest: Vec<DVec3> = ring
        .iter()
        .map(|&(i, _)| surface.rest()[i as usize])
        .collect();
    let fixed: Vec<bool> = ring
        .iter()
        .map(|&(i, d)| surface.is_fixed(i) || d == outer)
        .collect();
    let tris: Vec<[u32; 3]> = surface
        .triangles()
        .iter()
        .filter(|t| t.iter().all(|&i| local[i as usize] != NONE))
        .map(|t| t.map(|i| local[i as usize]))
        .collect();
    let patch = SpringSurface::patch(rest, tris, fixed)?;
    Ok((ring, patch))
}

/// The probe's contact offsets (contact position minus rest position) of the patch's coarse
/// nodes and of its subdivided slots (rest positions `fine_rest`), from the whole surface's
/// contact positions `contact` (a patch's own would be wrong at its cut).
fn contact_offsets(
    surface: &SpringSurface,
    patch: &SpringSurface,
    ring: &[(u32, u32)],
    contact: &ContactRest,
    fine_rest: &[DVec3],
) -> (Vec<DVec3>, Vec<DVec3>) {
    let nc = patch.node_count();
    let global = |i: u32| ring[i as usize].0;
    let coarse_offset = ring
        .iter()
        .map(|&(i, _)| contact.positions[i as usize] - surface.rest()[i as usize])
        .collect();
    let mut fine_offset = vec![DVec3::ZERO; fine_rest.len()];
    for i in 0..nc {
        let g = global(i as u32) as usize;
        fine_offset[i] = contact.positions[g] - fine_rest[i];
    }
    for (e, &[a, b]) in patch.edges().iter().enumerate() {
        if let Some(ge) = surface.edge_between(global(a), global(b)) {
            let slot = surface.node_count() + ge as usize;
            fine_offset[nc + e] = contact.positions[slot] - fine_rest[nc + e];
        }
    }
    (coarse_offset, fine_offset)
}
