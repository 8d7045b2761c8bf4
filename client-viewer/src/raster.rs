//! `raster`: a small deterministic software rasterizer for the deformed surface.
//!
//! An [`Image`] holds an RGB buffer and a z-buffer (view depth in metres, nearest wins).
//! [`Camera::auto_frame`] places a perspective camera around the keyframe's bounding box, and
//! [`render_surface`] draws a [`SurfaceView`]: the triangles with two-sided Lambert shading
//! (a headlight plus a key light from the upper left), coloured blue -> red by each vertex's
//! displacement from its rest position; the probe as a shaded sphere; the contact force as a
//! 3-D arrow (shaft + cone) starting at the probe centre. An optional text-free colour bar shows
//! the colormap.
//!
//! Vectors are `glam::DVec3` (metres or newtons, scene frame); everything is plain `f64`
//! arithmetic in a fixed order on one thread, so the same input gives the same bytes on every
//! run (the PNG encoder is deterministic too). Neighbours: [`crate::viewer`]
//! feeds it frames; nothing here knows about gRPC.

use std::io::Write;
use std::path::Path;

use glam::DVec3;

use crate::ClientError;

/// How displacement magnitudes map onto the blue -> red colormap.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DisplacementScale {
    /// Red is the largest displacement in the frame being drawn (at least 1 um, so an
    /// undeformed surface is uniformly blue).
    Auto,
    /// Red is this displacement in metres (larger ones saturate).
    FixedM(f64),
}

/// Picture and camera parameters. Plain data with a [`Default`] that suits a left ventricle
/// with its long axis on z and the apex at -z.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderParams {
    /// Picture width in pixels.
    pub width: u32,
    /// Picture height in pixels.
    pub height: u32,
    /// Direction from the model centre towards the camera (scene frame, any length).
    /// Default `(1, 1, 0.4)`: from +x+y, slightly above.
    pub view_from: DVec3,
    /// Scene direction that appears upwards in the picture (any length). Default +z.
    pub up: DVec3,
    /// Vertical field of view in degrees.
    pub fov_y_deg: f64,
    /// Colour scale of the displacement magnitude.
    pub displacement_scale: DisplacementScale,
    /// Force arrow length per newton of contact force, metres per newton (default 100 mm/N: soft-tissue contact forces are about 0.1 N).
    pub force_scale_m_per_n: f64,
    /// Background colour, sRGB bytes.
    pub background: [u8; 3],
    /// Draw a text-free colour bar at the right edge.
    pub legend: bool,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            width: 640,
            height: 480,
            view_from: DVec3::new(1.0, 1.0, 0.4),
            up: DVec3::Z,
            fov_y_deg: 30.0,
            displacement_scale: DisplacementScale::Auto,
            force_scale_m_per_n: 0.1,
            background: [24, 26, 32],
            legend: true,
        }
    }
}

impl RenderParams {
    /// Checks ranges (sizes 1..=8192, finite non-zero directions, field of view in (1, 170)
    /// degrees, non-negative finite scales).
    ///
    /// # Errors
    /// [`ClientError::InvalidConfig`] naming the first bad value.
    pub fn validate(&self) -> Result<(), ClientError> {
        let bad = |m: &str| Err(ClientError::InvalidConfig(m.to_string()));
        if !(1..=8192).contains(&self.width) || !(1..=8192).contains(&self.height) {
            return bad("width and height must be 1..=8192 pixels");
        }
        if self.view_from.try_normalize().is_none() || self.up.try_normalize().is_none() {
            return bad("view direction and up vector must be finite and non-zero");
        }
        if !(self.fov_y_deg > 1.0 && self.fov_y_deg < 170.0) {
            return bad("field of view must be between 1 and 170 degrees");
        }
        if let DisplacementScale::FixedM(m) = self.displacement_scale
            && !(m.is_finite() && m > 0.0)
        {
            return bad("fixed displacement scale must be a positive number of metres");
        }
        if !(self.force_scale_m_per_n.is_finite() && self.force_scale_m_per_n >= 0.0) {
            return bad("force scale must be a finite, non-negative number of metres per newton");
        }
        Ok(())
    }
}

/// A perspective pinhole camera. Build it with [`Camera::auto_frame`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Eye position, metres (scene frame).
    pub eye: DVec3,
    /// Unit viewing direction (from the eye into the scene).
    pub forward: DVec3,
    /// Unit picture-right direction.
    pub right: DVec3,
    /// Unit picture-up direction.
    pub up: DVec3,
    /// Focal length in pixels (`height / 2 / tan(fov_y / 2)`).
    pub focal_px: f64,
    /// Picture width, pixels.
    pub width: u32,
    /// Picture height, pixels.
    pub height: u32,
}

/// Closest view depth that is drawn, as a fraction of the model radius (near plane).
const NEAR_FRACTION: f64 = 1e-3;

impl Camera {
    /// Frames the axis-aligned box `[min_m, max_m]` (metres): looks at its centre from the
    /// direction `params.view_from`, far enough that the box's bounding sphere fits the smaller
    /// of the two fields of view with a 10 % margin.
    ///
    /// A degenerate or non-finite box falls back to a 0.1 m box at the origin, so a camera always
    /// exists. Call [`RenderParams::validate`] first; invalid directions fall back to defaults.
    pub fn auto_frame(min_m: DVec3, max_m: DVec3, params: &RenderParams) -> Camera {
        let (min_m, max_m) = if min_m.is_finite() && max_m.is_finite() {
            (min_m, max_m)
        } else {
            (DVec3::splat(-0.05), DVec3::splat(0.05))
        };
        let center = (min_m + max_m) * 0.5;
        let radius = ((max_m - min_m).length() * 0.5).max(1e-6);
        let (w, h) = (params.width.max(1), params.height.max(1));
        let fov_y = params.fov_y_deg.clamp(1.0, 170.0).to_radians();
        let aspect = w as f64 / h as f64;
        let fov_x = 2.0 * ((fov_y * 0.5).tan() * aspect).atan();
        let fov = fov_y.min(fov_x);
        let distance = radius / (fov * 0.5).sin() * 1.1;
        let from = params
            .view_from
            .try_normalize()
            .unwrap_or(DVec3::new(1.0, 1.0, 0.4));
        let forward = -from;
        let mut up_hint = params.up.try_normalize().unwrap_or(DVec3::Z);
        if forward.cross(up_hint).length() < 1e-6 {
            // Looking along the up vector: any perpendicular will do.
            up_hint = if forward.x.abs() < 0.9 {
                DVec3::X
            } else {
                DVec3::Y
            };
        }
        let right = forward.cross(up_hint).try_normalize().unwrap_or(DVec3::X);
        let up = right.cross(forward);
        Camera {
            eye: center + from * distance,
            forward,
            right,
            up,
            focal_px: h as f64 * 0.5 / (fov_y * 0.5).tan(),
            width: w,
            height: h,
        }
    }

    /// Projects a scene point (metres) to `(x_px, y_px, depth_m)`: pixel coordinates with the
    /// origin at the top-left corner (y down), and the distance along the viewing direction.
    /// `None` when the point is behind the near plane or not finite.
    pub fn project(&self, p: DVec3, near_m: f64) -> Option<(f64, f64, f64)> {
        let d = p - self.eye;
        let z = d.dot(self.forward);
        if z.is_nan() || z <= near_m || !z.is_finite() {
            return None;
        }
        let x = self.width as f64 * 0.5 + d.dot(self.right) / z * self.focal_px;
        let y = self.height as f64 * 0.5 - d.dot(self.up) / z * self.focal_px;
        (x.is_finite() && y.is_finite()).then_some((x, y, z))
    }

    /// Unit direction of the ray from the eye through the pixel point `(x_px, y_px)`.
    fn ray(&self, x: f64, y: f64) -> DVec3 {
        let dx = (x - self.width as f64 * 0.5) / self.focal_px;
        let dy = -(y - self.height as f64 * 0.5) / self.focal_px;
        let d = self.forward + (self.right * dx + self.up * dy);
        d.try_normalize().unwrap_or(self.forward)
    }
}

/// One corner of a triangle in picture space, for [`Image::fill_triangle`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScreenVertex {
    /// Column in pixels, from the left edge (pixel centres at `i + 0.5`).
    pub x: f64,
    /// Row in pixels, from the top edge.
    pub y: f64,
    /// View depth in metres, > 0; smaller is nearer.
    pub depth: f64,
    /// Linear RGB in `[0, 1]` (clamped when written).
    pub color: [f64; 3],
}

/// An RGB picture with a z-buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
    depth: Vec<f64>,
}

fn to_byte(c: f64) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Image {
    /// A `width x height` picture filled with `background`, all depths at infinity.
    pub fn new(width: u32, height: u32, background: [u8; 3]) -> Image {
        let n = width as usize * height as usize;
        let mut rgb = Vec::with_capacity(n * 3);
        for _ in 0..n {
            rgb.extend_from_slice(&background);
        }
        Image {
            width,
            height,
            rgb,
            depth: vec![f64::INFINITY; n],
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Row-major RGB bytes, 3 per pixel, top row first.
    pub fn rgb(&self) -> &[u8] {
        &self.rgb
    }

    /// Colour of pixel `(x, y)`.
    ///
    /// # Panics
    /// When `(x, y)` is outside the picture.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        assert!(x < self.width && y < self.height, "pixel out of range");
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Z-buffer value at pixel `(x, y)`, metres (infinity where nothing was drawn).
    ///
    /// # Panics
    /// When `(x, y)` is outside the picture.
    pub fn depth(&self, x: u32, y: u32) -> f64 {
        assert!(x < self.width && y < self.height, "pixel out of range");
        self.depth[y as usize * self.width as usize + x as usize]
    }

    /// Writes one pixel if `depth_m` is nearer than what is there. Returns whether it was written.
    fn plot(&mut self, x: usize, y: usize, depth_m: f64, color: [f64; 3]) -> bool {
        let i = y * self.width as usize + x;
        if depth_m < self.depth[i] {
            self.depth[i] = depth_m;
            self.rgb[i * 3] = to_byte(color[0]);
            self.rgb[i * 3 + 1] = to_byte(color[1]);
            self.rgb[i * 3 + 2] = to_byte(color[2]);
            true
        } else {
            false
        }
    }

    /// Rasterizes a triangle with a depth test: every pixel whose centre lies inside or on an edge
    /// is written when nearer than the z-buffer. Depth is interpolated perspective-correctly
    /// (linearly in `1 / depth`), colour linearly in picture space (Gouraud). Either winding is
    /// accepted; degenerate, non-finite or behind-the-eye triangles draw nothing.
    ///
    /// Returns the number of pixels written.
    pub fn fill_triangle(&mut self, v: &[ScreenVertex; 3]) -> usize {
        let ok = v
            .iter()
            .all(|p| p.x.is_finite() && p.y.is_finite() && p.depth.is_finite() && p.depth > 0.0);
        if !ok {
            return 0;
        }
        // Edge function with the endpoints in a canonical order, so a shared edge gives exactly
        // opposite values in its two triangles (no cracks, no winding dependence).
        let edge = |a: &ScreenVertex, b: &ScreenVertex, px: f64, py: f64| {
            let raw = |a: &ScreenVertex, b: &ScreenVertex| {
                (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px - a.x)
            };
            if (a.x, a.y) > (b.x, b.y) {
                -raw(b, a)
            } else {
                raw(a, b)
            }
        };
        let area = edge(&v[0], &v[1], v[2].x, v[2].y);
        if area.abs() < 1e-12 {
            return 0;
        }
        let min_x = v.iter().map(|p| p.x).fold(f64::INFINITY, f64::min);
        let max_x = v.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max);
        let min_y = v.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
        let max_y = v.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max);
        let x0 = (min_x - 0.5).ceil().max(0.0) as i64;
        let x1 = ((max_x - 0.5).floor() as i64).min(self.width as i64 - 1);
        let y0 = (min_y - 0.5).ceil().max(0.0) as i64;
        let y1 = ((max_y - 0.5).floor() as i64).min(self.height as i64 - 1);
        let inv_d = [1.0 / v[0].depth, 1.0 / v[1].depth, 1.0 / v[2].depth];
        let mut written = 0;
        for y in y0..=y1 {
            let py = y as f64 + 0.5;
            for x in x0..=x1 {
                let px = x as f64 + 0.5;
                let sign = area.signum();
                let w0 = edge(&v[1], &v[2], px, py) * sign;
                let w1 = edge(&v[2], &v[0], px, py) * sign;
                let w2 = edge(&v[0], &v[1], px, py) * sign;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let sum = w0 + w1 + w2;
                if sum <= 0.0 {
                    continue;
                }
                let (b0, b1, b2) = (w0 / sum, w1 / sum, w2 / sum);
                let depth = 1.0 / (b0 * inv_d[0] + b1 * inv_d[1] + b2 * inv_d[2]);
                let mut c = [0.0; 3];
                for (k, ck) in c.iter_mut().enumerate() {
                    *ck = b0 * v[0].color[k] + b1 * v[1].color[k] + b2 * v[2].color[k];
                }
                if self.plot(x as usize, y as usize, depth, c) {
                    written += 1;
                }
            }
        }
        written
    }

    /// Encodes the picture as an 8-bit RGB PNG (deterministic bytes).
    ///
    /// # Errors
    /// [`ClientError::Png`] if the encoder fails (it does not for a well-formed image).
    pub fn encode_png(&self) -> Result<Vec<u8>, ClientError> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width, self.height);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut writer = enc.write_header()?;
            writer.write_image_data(&self.rgb)?;
            writer.finish()?;
        }
        Ok(out)
    }

    /// Writes the picture as a PNG file atomically: the bytes go to a temporary file in the same
    /// directory (`.<name>.tmp`), which is then renamed over `path`, so a reader never sees a
    /// half-written picture.
    ///
    /// # Errors
    /// [`ClientError::Io`] when the file cannot be created, written or renamed;
    /// [`ClientError::Png`] when encoding fails.
    pub fn write_png(&self, path: &Path) -> Result<(), ClientError> {
        let bytes = self.encode_png()?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "picture.png".to_string());
        let tmp = path.with_file_name(format!(".{name}.tmp"));
        let io = |p: &Path| {
            let p = p.to_path_buf();
            move |source| ClientError::Io { path: p, source }
        };
        let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        f.write_all(&bytes).map_err(io(&tmp))?;
        drop(f);
        std::fs::rename(&tmp, path).map_err(io(path))
    }
}

/// The blue -> red colormap ("cool to warm": blue, light grey, red) at `t` in `[0, 1]`,
/// linear RGB in `[0, 1]`. Values outside are clamped; NaN maps to blue.
pub fn colormap(t: f64) -> [f64; 3] {
    const STOPS: [[f64; 3]; 3] = [[0.23, 0.30, 0.75], [0.87, 0.87, 0.87], [0.71, 0.02, 0.15]];
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let (a, b, s) = if t < 0.5 {
        (STOPS[0], STOPS[1], t * 2.0)
    } else {
        (STOPS[1], STOPS[2], t * 2.0 - 1.0)
    };
    [
        a[0] + (b[0] - a[0]) * s,
        a[1] + (b[1] - a[1]) * s,
        a[2] + (b[2] - a[2]) * s,
    ]
}

/// The probe (haptic interaction point) as drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeView {
    /// Centre, metres (scene frame).
    pub position_m: DVec3,
    /// Radius, metres; the sphere is drawn only when finite and > 0.
    pub radius_m: f64,
    /// Contact force acting at the probe, newtons; drawn as an arrow when non-zero and finite.
    pub force_n: DVec3,
    /// Whether the probe touches the surface (changes its colour).
    pub in_contact: bool,
}

/// A surface to draw: topology, rest and current positions, and optionally the probe.
#[derive(Debug, Clone, Copy)]
pub struct SurfaceView<'a> {
    /// Rest positions, metres, xyz interleaved (`3 * n` values).
    pub rest_m: &'a [f32],
    /// Current positions, metres, xyz interleaved (`3 * n` values, same `n`).
    pub positions_m: &'a [f32],
    /// Triangles, three vertex indices each (`3 * t` values, all `< n`).
    pub triangles: &'a [u32],
    /// The probe, when there is one.
    pub probe: Option<ProbeView>,
}

/// Axis-aligned bounding box `(min, max)` of xyz-interleaved positions (metres), ignoring
/// non-finite values. `None` when there is no finite point.
pub fn bounding_box(positions_m: &[f32]) -> Option<(DVec3, DVec3)> {
    let mut min = DVec3::INFINITY;
    let mut max = DVec3::NEG_INFINITY;
    let mut any = false;
    for p in positions_m.chunks_exact(3) {
        let p = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        if !p.is_finite() {
            continue;
        }
        any = true;
        min = min.min(p);
        max = max.max(p);
    }
    any.then_some((min, max))
}

/// Directions towards the two lights in the scene frame: a headlight (from the eye) and a key
/// light from the upper left, behind the camera.
fn lights(cam: &Camera) -> (DVec3, DVec3) {
    let head = -cam.forward;
    let key = cam.right * -0.45 + cam.up * 0.75 + cam.forward * -0.5;
    (head, key.try_normalize().unwrap_or(head))
}

/// Lambert intensity for unit normal `n` (already turned towards the viewer): ambient 0.18,
/// headlight 0.55, key light 0.45, at most 1.
fn lambert(n: DVec3, head: DVec3, key: DVec3) -> f64 {
    (0.18 + 0.55 * n.dot(head).max(0.0) + 0.45 * n.dot(key).max(0.0)).min(1.0)
}

fn vertex(positions: &[f32], i: usize) -> DVec3 {
    DVec3::new(
        positions[3 * i] as f64,
        positions[3 * i + 1] as f64,
        positions[3 * i + 2] as f64,
    )
}

/// `color` (linear RGB) times the light intensity `s`.
fn shade(color: [f64; 3], s: f64) -> [f64; 3] {
    color.map(|c| c * s)
}

/// Draws a triangle with flat per-vertex normals already chosen; turns normals towards the eye
/// (two-sided lighting) and shades each corner.
fn draw_shaded(
    img: &mut Image,
    cam: &Camera,
    near: f64,
    p: [DVec3; 3],
    normals: [DVec3; 3],
    colors: [[f64; 3]; 3],
) {
    let (head, key) = lights(cam);
    let mut sv = [ScreenVertex {
        x: 0.0,
        y: 0.0,
        depth: 0.0,
        color: [0.0; 3],
    }; 3];
    let face = (p[1] - p[0]).cross(p[2] - p[0]);
    let centroid = (p[0] + p[1] + p[2]) * (1.0 / 3.0);
    let to_eye = cam.eye - centroid;
    let flip = face.dot(to_eye) < 0.0;
    let face_n = if flip { -face } else { face };
    for k in 0..3 {
        let Some((x, y, d)) = cam.project(p[k], near) else {
            return;
        };
        let mut n = normals[k];
        if n.dot(face_n) < 0.0 {
            n = -n;
        }
        let s = lambert(n, head, key);
        sv[k] = ScreenVertex {
            x,
            y,
            depth: d,
            color: shade(colors[k], s),
        };
    }
    img.fill_triangle(&sv);
}

/// Renders `view` seen by `cam` into a new picture of `params.width x params.height`.
///
/// Vertex normals are area-weighted averages of the adjacent triangle normals; colours come from
/// [`colormap`] of `|position - rest| / scale` (see [`DisplacementScale`]). Triangles whose indices
/// are out of range or whose corners are not finite are skipped (the viewer rejects such frames
/// before they get here). The probe and force arrow are drawn with the same z-buffer, so the body
/// hides them where it is in front.
pub fn render_surface(view: &SurfaceView<'_>, cam: &Camera, params: &RenderParams) -> Image {
    let mut img = Image::new(cam.width, cam.height, params.background);
    let n = view.positions_m.len() / 3;
    let radius = bounding_box(view.rest_m)
        .map(|(a, b)| (b - a).length() * 0.5)
        .unwrap_or(0.05)
        .max(1e-6);
    let near = radius * NEAR_FRACTION;

    // Per-vertex displacement and its colour scale.
    let same_rest = view.rest_m.len() == view.positions_m.len();
    let disp: Vec<f64> = (0..n)
        .map(|i| {
            if same_rest {
                (vertex(view.positions_m, i) - vertex(view.rest_m, i)).length()
            } else {
                0.0
            }
        })
        .collect();
    let scale_m = match params.displacement_scale {
        DisplacementScale::FixedM(m) => m,
        DisplacementScale::Auto => disp
            .iter()
            .copied()
            .filter(|d| d.is_finite())
            .fold(0.0, f64::max)
            .max(1e-6),
    };

    // Area-weighted vertex normals.
    let tris: Vec<[usize; 3]> = view
        .triangles
        .chunks_exact(3)
        .map(|t| [t[0] as usize, t[1] as usize, t[2] as usize])
        .filter(|t| t.iter().all(|&i| i < n))
        .collect();
    let mut normals = vec![DVec3::ZERO; n];
    for t in &tris {
        let p = t.map(|i| vertex(view.positions_m, i));
        let f = (p[1] - p[0]).cross(p[2] - p[0]);
        if f.is_finite() {
            for &i in t {
                normals[i] += f;
            }
        }
    }
    for t in &tris {
        let p = t.map(|i| vertex(view.positions_m, i));
        if !p.iter().all(|q| q.is_finite()) {
            continue;
        }
        let face = (p[1] - p[0])
            .cross(p[2] - p[0])
            .try_normalize()
            .unwrap_or(cam.forward);
        let ns = t.map(|i| normals[i].try_normalize().unwrap_or(face));
        let cs = t.map(|i| colormap(disp[i] / scale_m));
        draw_shaded(&mut img, cam, near, p, ns, cs);
    }

    if let Some(probe) = view.probe {
        draw_probe(&mut img, cam, near, &probe, radius, params);
    }
    if params.legend {
        draw_legend(&mut img);
    }
    img
}

/// Ray-casts the probe sphere and builds the force arrow out of triangles.
fn draw_probe(
    img: &mut Image,
    cam: &Camera,
    near: f64,
    probe: &ProbeView,
    model_radius_m: f64,
    params: &RenderParams,
) {
    let c = probe.position_m;
    if !c.is_finite() {
        return;
    }
    let r = probe.radius_m;
    if r.is_finite() && r > 0.0 {
        let color = if probe.in_contact {
            [0.95, 0.62, 0.15]
        } else {
            [0.55, 0.80, 0.55]
        };
        draw_sphere(img, cam, c, r, color);
    }
    let f = probe.force_n;
    let f_mag = f.length();
    let len = f_mag * params.force_scale_m_per_n;
    if f.is_finite() && f_mag > 0.0 && len.is_finite() && len > 0.0 {
        let shaft_r = (model_radius_m * 0.012).max(len * 0.03);
        let head_r = shaft_r * 2.5;
        let head_len = (shaft_r * 7.0).min(len * 0.4);
        draw_arrow(
            img,
            cam,
            near,
            c,
            f * (1.0 / f_mag),
            len,
            shaft_r,
            head_r,
            head_len,
        );
    }
}

fn draw_sphere(img: &mut Image, cam: &Camera, c: DVec3, r: f64, color: [f64; 3]) {
    let (head, key) = lights(cam);
    let oc = cam.eye - c;
    let zc = (c - cam.eye).dot(cam.forward);
    // Picture-space bounding square of the sphere (the whole picture when the eye is close).
    let (x0, x1, y0, y1) = match cam.project(c, r * 1.01) {
        Some((x, y, _)) if zc > r * 1.01 => {
            let rad = r * cam.focal_px / (zc - r).max(1e-12) * 1.5 + 2.0;
            (x - rad, x + rad, y - rad, y + rad)
        }
        _ => (0.0, cam.width as f64, 0.0, cam.height as f64),
    };
    let xs = x0.floor().max(0.0) as i64..=(x1.ceil() as i64).min(cam.width as i64 - 1);
    let ys = y0.floor().max(0.0) as i64..=(y1.ceil() as i64).min(cam.height as i64 - 1);
    for y in ys {
        for x in xs.clone() {
            let d = cam.ray(x as f64 + 0.5, y as f64 + 0.5);
            let b = oc.dot(d);
            let cc = oc.dot(oc) - r * r;
            let disc = b * b - cc;
            if disc < 0.0 {
                continue;
            }
            let t = -b - disc.sqrt();
            if t <= 0.0 {
                continue;
            }
            let hit = cam.eye + d * t;
            let n = (hit - c) * (1.0 / r);
            let s = lambert(n, head, key);
            img.plot(
                x as usize,
                y as usize,
                t * d.dot(cam.forward),
                shade(color, s),
            );
        }
    }
}

/// An arrow from `start` along unit `dir`: a 12-sided cylinder (radius `shaft_r`) and a cone
/// (base radius `head_r`, length `head_len`), total length `len` (all metres), flat shaded.
#[allow(clippy::too_many_arguments)]
fn draw_arrow(
    img: &mut Image,
    cam: &Camera,
    near: f64,
    start: DVec3,
    dir: DVec3,
    len: f64,
    shaft_r: f64,
    head_r: f64,
    head_len: f64,
) {
    const SIDES: usize = 12;
    const COLOR: [f64; 3] = [0.98, 0.86, 0.20];
    let helper = if dir.x.abs() < 0.9 {
        DVec3::X
    } else {
        DVec3::Y
    };
    let Some(u) = dir.cross(helper).try_normalize() else {
        return;
    };
    let v = dir.cross(u);
    let ring = |center: DVec3, r: f64, k: usize| {
        let a = std::f64::consts::TAU * k as f64 / SIDES as f64;
        center + (u * (r * a.cos()) + v * (r * a.sin()))
    };
    let base = start + dir * (len - head_len).max(0.0);
    let tip = start + dir * len;
    let mut tri = |p: [DVec3; 3]| {
        let n = (p[1] - p[0])
            .cross(p[2] - p[0])
            .try_normalize()
            .unwrap_or(dir);
        draw_shaded(img, cam, near, p, [n; 3], [COLOR; 3]);
    };
    for k in 0..SIDES {
        let (a0, a1) = (ring(start, shaft_r, k), ring(start, shaft_r, k + 1));
        let (b0, b1) = (ring(base, shaft_r, k), ring(base, shaft_r, k + 1));
        tri([a0, a1, b1]);
        tri([a0, b1, b0]);
        let (h0, h1) = (ring(base, head_r, k), ring(base, head_r, k + 1));
        tri([h0, h1, tip]);
        tri([h0, base, h1]);
    }
}

/// A text-free colour bar at the right edge: the colormap from blue (bottom, no displacement)
/// to red (top, full scale), with a dark frame. Drawn over everything.
fn draw_legend(img: &mut Image) {
    let (w, h) = (img.width as usize, img.height as usize);
    if w < 40 || h < 40 {
        return;
    }
    let (x0, x1) = (w - 18, w - 8);
    let (y0, y1) = (h * 3 / 10, h * 7 / 10);
    for y in y0 - 1..=y1 {
        for x in x0 - 1..=x1 {
            let frame = x == x0 - 1 || x == x1 || y == y0 - 1 || y == y1;
            let c = if frame {
                [0.05, 0.05, 0.05]
            } else {
                colormap((y1 - 1 - y) as f64 / (y1 - y0 - 1).max(1) as f64)
            };
            let i = y * w + x;
            img.depth[i] = f64::NEG_INFINITY;
            img.rgb[i * 3] = to_byte(c[0]);
            img.rgb[i * 3 + 1] = to_byte(c[1]);
            img.rgb[i * 3 + 2] = to_byte(c[2]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sv(x: f64, y: f64, depth: f64, color: [f64; 3]) -> ScreenVertex {
        ScreenVertex { x, y, depth, color }
    }

    #[test]
    fn single_triangle_covers_expected_pixels() {
        let mut img = Image::new(16, 16, [0, 0, 0]);
        let white = [1.0; 3];
        let n = img.fill_triangle(&[
            sv(0.0, 0.0, 1.0, white),
            sv(10.0, 0.0, 1.0, white),
            sv(0.0, 10.0, 1.0, white),
        ]);
        // Pixel (i, j) has its centre at (i + 0.5, j + 0.5): inside when i + j <= 9.
        assert_eq!(n, 55);
        for y in 0..16 {
            for x in 0..16 {
                let inside = x + y <= 9;
                let expect = if inside { [255; 3] } else { [0; 3] };
                assert_eq!(img.pixel(x, y), expect, "pixel {x},{y}");
            }
        }
    }

    #[test]
    fn winding_does_not_matter() {
        let mut a = Image::new(16, 16, [0, 0, 0]);
        let mut b = a.clone();
        let p = [
            sv(1.0, 1.0, 1.0, [1.0; 3]),
            sv(13.0, 2.0, 1.0, [1.0; 3]),
            sv(4.0, 12.0, 1.0, [1.0; 3]),
        ];
        a.fill_triangle(&p);
        b.fill_triangle(&[p[0], p[2], p[1]]);
        // Same pixels; depths may differ in the last bit (summation order).
        assert_eq!(a.rgb(), b.rgb());
        assert!(a.rgb().contains(&255));
    }

    #[test]
    fn z_buffer_keeps_the_nearest() {
        let red = [1.0, 0.0, 0.0];
        let green = [0.0, 1.0, 0.0];
        let tri = |d: f64, c| [sv(0.0, 0.0, d, c), sv(20.0, 0.0, d, c), sv(0.0, 20.0, d, c)];
        // Near first, far second: the far one must not overwrite.
        let mut img = Image::new(8, 8, [0, 0, 0]);
        img.fill_triangle(&tri(1.0, red));
        assert_eq!(img.fill_triangle(&tri(2.0, green)), 0);
        assert_eq!(img.pixel(2, 2), [255, 0, 0]);
        assert_eq!(img.depth(2, 2), 1.0);
        // Far first, near second: the near one wins.
        let mut img = Image::new(8, 8, [0, 0, 0]);
        img.fill_triangle(&tri(2.0, green));
        img.fill_triangle(&tri(1.0, red));
        assert_eq!(img.pixel(2, 2), [255, 0, 0]);
    }

    #[test]
    fn png_round_trip_has_same_size_and_pixels() {
        let mut img = Image::new(33, 17, [10, 20, 30]);
        img.fill_triangle(&[
            sv(0.0, 0.0, 1.0, [1.0, 0.5, 0.0]),
            sv(30.0, 3.0, 1.0, [0.0, 1.0, 0.0]),
            sv(5.0, 16.0, 1.0, [0.0, 0.0, 1.0]),
        ]);
        let dir = std::env::temp_dir().join(format!("raster-rt-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("rt.png");
        img.write_png(&path).unwrap();
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (33, 17));
        assert_eq!(&buf[..info.buffer_size()], img.rgb());
        assert!(!dir.join(".rt.png.tmp").exists());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A unit octahedron around the origin (radius 0.02 m) with one vertex displaced.
    fn octahedron(dz_m: f32) -> (Vec<f32>, Vec<f32>, Vec<u32>) {
        let r = 0.02;
        let rest = vec![
            r, 0., 0., -r, 0., 0., 0., r, 0., 0., -r, 0., 0., 0., r, 0., 0., -r,
        ];
        let mut pos = rest.clone();
        pos[14] += dz_m;
        let tris = vec![
            0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5,
        ];
        (rest, pos, tris)
    }

    fn render_octahedron(dz_m: f32, probe: Option<ProbeView>) -> Image {
        let (rest, pos, tris) = octahedron(dz_m);
        let params = RenderParams {
            width: 96,
            height: 72,
            ..RenderParams::default()
        };
        let (a, b) = bounding_box(&rest).unwrap();
        let cam = Camera::auto_frame(a, b, &params);
        render_surface(
            &SurfaceView {
                rest_m: &rest,
                positions_m: &pos,
                triangles: &tris,
                probe,
            },
            &cam,
            &params,
        )
    }

    /// FNV-1a over bytes: a stable fingerprint of a picture (std's hashers may change between
    /// Rust releases).
    fn fnv1a(bytes: &[u8]) -> u64 {
        bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
            (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
        })
    }

    /// A closed, dented prolate ellipsoid (radii 25, 25, 45 mm; `nu x nv` quads split in two):
    /// `(rest, positions, triangles)`.
    fn dented_ellipsoid(nu: u32, nv: u32) -> (Vec<f32>, Vec<f32>, Vec<u32>) {
        let (a, c) = (0.025f32, 0.045f32);
        let mut rest = Vec::new();
        for j in 0..=nv {
            let th = std::f32::consts::PI * j as f32 / nv as f32;
            for i in 0..nu {
                let ph = std::f32::consts::TAU * i as f32 / nu as f32;
                rest.extend([
                    a * th.sin() * ph.cos(),
                    a * th.sin() * ph.sin(),
                    c * th.cos(),
                ]);
            }
        }
        let mut tris = Vec::new();
        for j in 0..nv {
            for i in 0..nu {
                let i1 = (i + 1) % nu;
                let (p, q, r, s) = (j * nu + i, j * nu + i1, (j + 1) * nu + i, (j + 1) * nu + i1);
                tris.extend([p, q, s, p, s, r]);
            }
        }
        let centre = [0.0177f32, 0.0177, -0.005];
        let mut pos = rest.clone();
        for v in pos.chunks_exact_mut(3) {
            let d2 = (v[0] - centre[0]).powi(2)
                + (v[1] - centre[1]).powi(2)
                + (v[2] - centre[2]).powi(2);
            let w = 0.004 * (-d2 / (2.0 * 0.008f32.powi(2))).exp();
            let r = (v[0] * v[0] + v[1] * v[1]).sqrt().max(1e-9);
            v[0] -= w * v[0] / r;
            v[1] -= w * v[1] / r;
        }
        (rest, pos, tris)
    }

    /// Regression guard for refactors of the vector arithmetic: the exact pictures of three
    /// scenes (shaded surface with per-vertex colours, probe sphere, oblique force arrow,
    /// legend; a second camera looking along its up vector; a fixed colour scale) are pinned by
    /// their RGB fingerprints. The values were taken from the rasterizer before it moved to
    /// `glam::DVec3`. A mismatch means the picture changed: look at it before updating a value.
    #[test]
    fn pictures_match_the_pinned_fingerprints() {
        let (rest, pos, tris) = dented_ellipsoid(40, 20);
        let probe = ProbeView {
            position_m: DVec3::new(0.0184, 0.0184, -0.005),
            radius_m: 0.004,
            force_n: DVec3::new(0.6, 0.45, 0.2),
            in_contact: true,
        };
        let view = SurfaceView {
            rest_m: &rest,
            positions_m: &pos,
            triangles: &tris,
            probe: Some(probe),
        };
        let (a, b) = bounding_box(&rest).unwrap();
        let side = RenderParams {
            width: 200,
            height: 150,
            ..RenderParams::default()
        };
        let top = RenderParams {
            width: 120,
            height: 120,
            view_from: DVec3::Z,
            up: DVec3::new(0.0, 0.0, 2.0),
            displacement_scale: DisplacementScale::FixedM(0.01),
            legend: false,
            ..RenderParams::default()
        };
        let octahedron = render_octahedron(
            0.004,
            Some(ProbeView {
                position_m: DVec3::new(0.005, -0.004, 0.03),
                radius_m: 0.003,
                force_n: DVec3::new(-0.2, 0.3, -1.0),
                in_contact: false,
            }),
        );
        let got = [
            fnv1a(render_surface(&view, &Camera::auto_frame(a, b, &side), &side).rgb()),
            fnv1a(render_surface(&view, &Camera::auto_frame(a, b, &top), &top).rgb()),
            fnv1a(octahedron.rgb()),
        ];
        let pinned: [u64; 3] = [
            0xf2ab_57ee_75d3_c26a,
            0xea44_f76f_259a_3493,
            0x709a_57ad_73bb_5761,
        ];
        assert_eq!(got, pinned, "got {got:#x?}");
    }

    #[test]
    fn rendering_is_deterministic_and_reacts_to_motion() {
        let probe = ProbeView {
            position_m: DVec3::new(0.0, 0.0, 0.03),
            radius_m: 0.003,
            force_n: DVec3::Z,
            in_contact: true,
        };
        let a = render_octahedron(0.0, Some(probe)).encode_png().unwrap();
        let b = render_octahedron(0.0, Some(probe)).encode_png().unwrap();
        assert_eq!(a, b);
        let moved = render_octahedron(0.005, Some(probe)).encode_png().unwrap();
        assert_ne!(a, moved);
    }

    #[test]
    fn surface_is_centred_and_probe_is_visible() {
        let img = render_octahedron(0.0, None);
        // The model is framed around the picture centre.
        assert!(img.depth(48, 36).is_finite());
        assert_eq!(img.pixel(0, 0), RenderParams::default().background);
        let probe = ProbeView {
            position_m: DVec3::new(0.0, 0.0, 0.03),
            radius_m: 0.004,
            force_n: DVec3::ZERO,
            in_contact: false,
        };
        let with = render_octahedron(0.0, Some(probe));
        let changed = with
            .rgb()
            .iter()
            .zip(img.rgb())
            .filter(|(a, b)| a != b)
            .count();
        assert!(changed > 0);
        // A non-finite radius draws no sphere.
        let hidden = render_octahedron(
            0.0,
            Some(ProbeView {
                radius_m: f64::NAN,
                ..probe
            }),
        );
        assert_eq!(hidden, img);
    }

    #[test]
    fn colormap_goes_blue_to_red() {
        let lo = colormap(0.0);
        let hi = colormap(1.0);
        assert!(lo[2] > lo[0] && hi[0] > hi[2]);
        assert_eq!(colormap(f64::NAN), lo);
        assert_eq!(colormap(7.0), hi);
    }

    #[test]
    fn params_validation() {
        assert!(RenderParams::default().validate().is_ok());
        let bad = RenderParams {
            width: 0,
            ..RenderParams::default()
        };
        assert!(bad.validate().is_err());
        let bad = RenderParams {
            displacement_scale: DisplacementScale::FixedM(-1.0),
            ..RenderParams::default()
        };
        assert!(bad.validate().is_err());
    }
}
