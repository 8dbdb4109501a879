//! CPU z-buffer rendering of meshes to PNG previews.
//!
//! Each view is rasterised on its own (in parallel, so the bytes do not depend on the thread count) at
//! `supersample`-times the tile size, shaded per pixel in linear light (ambient + two Lambert lights + a
//! Blinn-Phong highlight, back faces in a muted colour so open surfaces read), then box-filtered down and
//! gamma-encoded. Each view is framed on the projected extent of everything drawn. An optional ghost mesh
//! (e.g. the truth) is blended translucently where it lies in front of the mesh or where there is no mesh;
//! optional 3D line segments (frame outlines) are drawn solid where visible and faint where hidden.

use std::path::Path;

use glam::DVec3;
use rayon::prelude::*;

use crate::mesh::Mesh;
use crate::{Error, Result};

/// An 8-bit RGB picture, rows top to bottom.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    /// `width * height * 3` bytes, R G B per pixel.
    pub pixels: Vec<u8>,
}

impl RgbImage {
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.pixels[i], self.pixels[i + 1], self.pixels[i + 2]]
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Projection {
    /// Perspective with the given vertical field of view (degrees); the framing still fills the tile.
    Perspective {
        fov_y_deg: f64,
    },
    Orthographic,
}

/// A viewpoint: the camera looks at the content from direction (azimuth, elevation), z up. Azimuth 0 looks
/// along +y (from -y), 90 looks along -x (from +x); elevation 90 looks straight down -z.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    pub azimuth_deg: f64,
    pub elevation_deg: f64,
}

impl View {
    pub const FRONT: View = View {
        azimuth_deg: 0.0,
        elevation_deg: 0.0,
    };
    pub const SIDE: View = View {
        azimuth_deg: 90.0,
        elevation_deg: 0.0,
    };
    pub const TOP: View = View {
        azimuth_deg: 0.0,
        elevation_deg: 90.0,
    };
    pub const OBLIQUE: View = View {
        azimuth_deg: 35.0,
        elevation_deg: 30.0,
    };

    /// Unit vector from the scene towards the camera.
    fn eye_direction(self) -> DVec3 {
        let (az, el) = (
            self.azimuth_deg.to_radians(),
            self.elevation_deg.to_radians(),
        );
        DVec3::new(el.cos() * az.sin(), -el.cos() * az.cos(), el.sin())
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Width of the whole picture in pixels; views are square tiles in a grid of two columns.
    pub size_px: u32,
    pub projection: Projection,
    /// One tile per view (1 to 16).
    pub views: Vec<View>,
    /// Rendering resolution factor for anti-aliasing (1 to 4).
    pub supersample: u32,
    /// sRGB colours.
    pub mesh_colour: [u8; 3],
    pub back_colour: [u8; 3],
    pub background_top: [u8; 3],
    pub background_bottom: [u8; 3],
    /// 3D segments (mm) drawn over the mesh, e.g. ultrasound frame outlines.
    pub overlay_lines: Vec<[DVec3; 2]>,
    pub overlay_colour: [u8; 3],
    /// A second mesh shown translucently (e.g. the ground truth).
    pub ghost: Option<Mesh>,
    pub ghost_colour: [u8; 3],
    /// Opacity of the ghost, 0 to 1.
    pub ghost_opacity: f64,
    /// Small x (red), y (green), z (blue) axes in each tile's corner.
    pub axes: bool,
    /// One sRGB colour per mesh vertex (an error map), instead of `mesh_colour`; back faces show it
    /// darkened.
    pub vertex_colours: Option<Vec<[u8; 3]>>,
    /// A colour scale drawn in a strip under the views (the key to `vertex_colours`).
    pub colour_bar: Option<ColourBar>,
}

/// The key to a colour map: its colours from left to right, and labels at positions along it (0 = left
/// end, 1 = right end). Labels use digits, `.`, `-`, `>`, `m` and spaces.
#[derive(Debug, Clone, PartialEq)]
pub struct ColourBar {
    pub colours: Vec<[u8; 3]>,
    pub labels: Vec<(f64, String)>,
}

/// The key to [`distance_colour`](crate::metrics::distance_colour) on `scale_mm`, for a picture: the
/// ramp from 0 to the scale, labelled at 0, half the scale and the scale (in mm).
pub fn distance_colour_bar(scale_mm: f64) -> ColourBar {
    const STEPS: usize = 256;
    let short = |x: f64| format!("{}", (x * 1000.0).round() / 1000.0);
    ColourBar {
        colours: (0..STEPS)
            .map(|i| {
                crate::metrics::distance_colour(scale_mm * i as f64 / (STEPS - 1) as f64, scale_mm)
            })
            .collect(),
        labels: vec![
            (0.0, "0".into()),
            (0.5, short(scale_mm / 2.0)),
            (1.0, format!("{} mm", short(scale_mm))),
        ],
    }
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            size_px: 800,
            projection: Projection::Perspective { fov_y_deg: 25.0 },
            views: vec![View::FRONT, View::SIDE, View::TOP, View::OBLIQUE],
            supersample: 2,
            mesh_colour: [226, 196, 160],
            back_colour: [120, 140, 175],
            background_top: [46, 52, 64],
            background_bottom: [18, 20, 26],
            overlay_lines: Vec::new(),
            overlay_colour: [255, 210, 60],
            ghost: None,
            ghost_colour: [90, 200, 255],
            ghost_opacity: 0.35,
            axes: true,
            vertex_colours: None,
            colour_bar: None,
        }
    }
}

/// Renders `mesh` from every view in `options` into one picture (a grid of square tiles).
pub fn render_views(mesh: &Mesh, options: &RenderOptions) -> Result<RgbImage> {
    if !(16..=8192).contains(&options.size_px) {
        return Err(Error::InvalidInput(format!(
            "picture size must be 16 to 8192 pixels, got {}",
            options.size_px
        )));
    }
    if options.views.is_empty() || options.views.len() > 16 {
        return Err(Error::InvalidInput(format!(
            "need 1 to 16 views, got {}",
            options.views.len()
        )));
    }
    if !(1..=4).contains(&options.supersample) {
        return Err(Error::InvalidInput(format!(
            "supersample must be 1 to 4, got {}",
            options.supersample
        )));
    }
    if let Projection::Perspective { fov_y_deg } = options.projection
        && !(fov_y_deg > 0.0 && fov_y_deg < 170.0)
    {
        return Err(Error::InvalidInput(format!(
            "field of view must be between 0 and 170 degrees, got {fov_y_deg}"
        )));
    }
    if !(0.0..=1.0).contains(&options.ghost_opacity) {
        return Err(Error::InvalidInput(format!(
            "ghost opacity must be 0 to 1, got {}",
            options.ghost_opacity
        )));
    }
    if let Some(colours) = &options.vertex_colours
        && colours.len() != mesh.vertices.len()
    {
        return Err(Error::InvalidInput(format!(
            "{} vertex colours for {} vertices",
            colours.len(),
            mesh.vertices.len()
        )));
    }
    let columns = if options.views.len() == 1 { 1 } else { 2 };
    let rows = options.views.len().div_ceil(columns) as u32;
    let tile = options.size_px / columns as u32;
    // Each rendering thread holds (tile * supersample)^2 pixels of ~40 bytes (colour and depth, twice
    // with a ghost): cap that at 4096^2 (~670 MB), and the finished picture at 64 M pixels.
    let rendered = tile as u64 * options.supersample as u64;
    let picture = tile as u64 * columns as u64 * tile as u64 * rows as u64;
    if rendered > 4096 || picture > 1 << 26 {
        return Err(Error::ResourceLimit(format!(
            "a {}-pixel picture of {} views at supersample {} is too large to render; \
             use a smaller size or supersample (tile x supersample <= 4096)",
            options.size_px,
            options.views.len(),
            options.supersample
        )));
    }
    let scene = Scene::new(mesh, options);
    let tiles: Vec<Vec<u8>> = options
        .views
        .par_iter()
        .map(|&view| render_tile(&scene, view, tile, options))
        .collect();

    let width = tile * columns as u32;
    let height = tile * rows;
    let mut pixels = vec![0u8; width as usize * height as usize * 3];
    for (k, tile_pixels) in tiles.iter().enumerate() {
        let (tx, ty) = ((k % columns) as u32 * tile, (k / columns) as u32 * tile);
        for y in 0..tile {
            let src = &tile_pixels[(y * tile * 3) as usize..((y + 1) * tile * 3) as usize];
            let dst = 3 * ((ty + y) as usize * width as usize + tx as usize);
            pixels[dst..dst + src.len()].copy_from_slice(src);
        }
    }
    // Thin separators between tiles.
    let separator = [70u8, 76, 88];
    for k in 1..columns as u32 {
        for y in 0..height {
            let i = 3 * (y as usize * width as usize + (k * tile) as usize);
            pixels[i..i + 3].copy_from_slice(&separator);
        }
    }
    for k in 1..rows {
        for x in 0..width {
            let i = 3 * ((k * tile) as usize * width as usize + x as usize);
            pixels[i..i + 3].copy_from_slice(&separator);
        }
    }
    let mut image = RgbImage {
        width,
        height,
        pixels,
    };
    if let Some(bar) = &options.colour_bar {
        append_colour_bar(&mut image, bar);
    }
    Ok(image)
}

/// 5 x 7 glyphs (rows top down, bit 4 = left column) for the colour bar's labels.
fn glyph(c: char) -> [u8; 7] {
    match c {
        '0' => [14, 17, 19, 21, 25, 17, 14],
        '1' => [4, 12, 4, 4, 4, 4, 14],
        '2' => [14, 17, 1, 2, 4, 8, 31],
        '3' => [31, 2, 4, 2, 1, 17, 14],
        '4' => [2, 6, 10, 18, 31, 2, 2],
        '5' => [31, 16, 30, 1, 1, 17, 14],
        '6' => [6, 8, 16, 30, 17, 17, 14],
        '7' => [31, 1, 2, 4, 8, 8, 8],
        '8' => [14, 17, 17, 14, 17, 17, 14],
        '9' => [14, 17, 17, 15, 1, 2, 12],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        '>' => [16, 8, 4, 2, 4, 8, 16],
        'm' => [0, 0, 26, 21, 21, 17, 17],
        _ => [0; 7],
    }
}

/// Adds a strip under `image` with the bar's colours across the middle 80 % of the width, a tick under
/// each label's position and the label centred below it.
fn append_colour_bar(image: &mut RgbImage, bar: &ColourBar) {
    if bar.colours.is_empty() {
        return;
    }
    let width = image.width as usize;
    let k = (width / 400).max(1); // text and bar scale, in pixels per font pixel
    let (bar_top, bar_height, tick, text_top) = (4 * k, 6 * k, 2 * k, 14 * k);
    let strip = text_top + 10 * k;
    let mut pixels = vec![0u8; width * strip * 3];
    for px in pixels.chunks_exact_mut(3) {
        px.copy_from_slice(&[18, 20, 26]);
    }
    let mut put = |x: usize, y: usize, c: [u8; 3]| {
        if x < width && y < strip {
            pixels[3 * (y * width + x)..3 * (y * width + x) + 3].copy_from_slice(&c);
        }
    };
    let (x0, x1) = (width / 10, width - width / 10);
    let span = (x1 - x0).max(1);
    for x in x0..x1 {
        let i = ((x - x0) * bar.colours.len() / span).min(bar.colours.len() - 1);
        for y in bar_top..bar_top + bar_height {
            put(x, y, bar.colours[i]);
        }
    }
    let text = [220, 224, 232];
    for (at, label) in &bar.labels {
        let x = x0 + (at.clamp(0.0, 1.0) * (span - 1) as f64).round() as usize;
        for y in bar_top + bar_height..bar_top + bar_height + tick {
            for dx in 0..k {
                put(x + dx, y, text);
            }
        }
        let label_width = label.chars().count() * 6 * k;
        let left = x
            .saturating_sub(label_width / 2)
            .min(width.saturating_sub(label_width));
        for (n, c) in label.chars().enumerate() {
            for (row, bits) in glyph(c).into_iter().enumerate() {
                for col in 0..5 {
                    if bits & (16 >> col) != 0 {
                        for (dx, dy) in (0..k).flat_map(|dx| (0..k).map(move |dy| (dx, dy))) {
                            put(left + (6 * n + col) * k + dx, text_top + row * k + dy, text);
                        }
                    }
                }
            }
        }
    }
    image.height += strip as u32;
    image.pixels.extend_from_slice(&pixels);
}

/// Encodes an image as an 8-bit RGB PNG (deterministic bytes).
pub fn encode_png(image: &RgbImage) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    crate::io::atomic::encode_png8(
        &mut out,
        image.width,
        image.height,
        png::ColorType::Rgb,
        &image.pixels,
    )
    .map_err(|e| Error::InvalidInput(format!("PNG encoding: {e}")))?;
    Ok(out)
}

/// Writes `image` as a PNG, atomically.
pub fn write_png(path: &Path, image: &RgbImage) -> Result<()> {
    crate::io::atomic::write_png_atomic(
        path,
        image.width,
        image.height,
        png::ColorType::Rgb,
        &image.pixels,
    )
}

/// A triangle's corners and per-corner unit normals (vertex normals, or the face normal three times).
type ShadedTriangle = ([DVec3; 3], [DVec3; 3]);

/// Triangles with their corners and shading normals gathered once for all views.
struct Surface {
    triangles: Vec<ShadedTriangle>,
    /// Per-corner linear colours, parallel to `triangles`, when the vertices have colours.
    corner_colours: Option<Vec<[[f32; 3]; 3]>>,
}

/// Back faces of a vertex-coloured surface show its colour at this brightness.
const BACK_FACE_SHADE: f32 = 0.55;

impl Surface {
    fn new(mesh: &Mesh) -> Self {
        Self::with_colours(mesh, None)
    }

    /// `colours` has one entry per vertex (checked by the caller).
    fn with_colours(mesh: &Mesh, colours: Option<&[[u8; 3]]>) -> Self {
        let n = mesh.vertices.len();
        let smooth = mesh.normals.len() == n;
        let kept: Vec<(&[u32; 3], ShadedTriangle)> = mesh
            .triangles
            .iter()
            .filter(|t| t.iter().all(|&i| (i as usize) < n))
            .filter_map(|t| {
                let p = t.map(|i| mesh.vertices[i as usize]);
                if !p.iter().all(|v| v.is_finite()) {
                    return None;
                }
                let face = (p[1] - p[0]).cross(p[2] - p[0]).try_normalize()?;
                let normals = if smooth {
                    t.map(|i| mesh.normals[i as usize].try_normalize().unwrap_or(face))
                } else {
                    [face; 3]
                };
                Some((t, (p, normals)))
            })
            .collect();
        let corner_colours = colours.map(|colours| {
            kept.iter()
                .map(|(t, _)| t.map(|i| linear(colours[i as usize])))
                .collect()
        });
        Surface {
            triangles: kept.into_iter().map(|(_, corners)| corners).collect(),
            corner_colours,
        }
    }

    fn points(&self) -> impl Iterator<Item = DVec3> + '_ {
        self.triangles.iter().flat_map(|(p, _)| p.iter().copied())
    }
}

struct Scene {
    mesh: Surface,
    ghost: Option<Surface>,
    lines: Vec<[DVec3; 2]>,
    /// Centre and radius of a sphere around everything drawn.
    centre: DVec3,
    radius: f64,
    empty: bool,
}

impl Scene {
    fn new(mesh: &Mesh, options: &RenderOptions) -> Self {
        let mesh = Surface::with_colours(mesh, options.vertex_colours.as_deref());
        let ghost = options.ghost.as_ref().map(Surface::new);
        let lines: Vec<[DVec3; 2]> = options
            .overlay_lines
            .iter()
            .filter(|l| l[0].is_finite() && l[1].is_finite())
            .copied()
            .collect();
        let all = || {
            mesh.points()
                .chain(ghost.iter().flat_map(|g| g.points()))
                .chain(lines.iter().flat_map(|l| l.iter().copied()))
        };
        let (lo, hi) = all().fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p), hi.max(p))
        });
        let empty = lo.x > hi.x;
        let (centre, radius) = if empty {
            (DVec3::ZERO, 1.0)
        } else {
            let c = (lo + hi) / 2.0;
            (c, ((hi - lo).length() / 2.0).max(1e-6))
        };
        Scene {
            mesh,
            ghost,
            lines,
            centre,
            radius,
            empty,
        }
    }
}

/// Maps world points to supersampled tile pixels; `depth` is larger for nearer points and varies
/// linearly across the screen (1/z in perspective, -z in orthographic).
struct Camera {
    eye: DVec3,
    right: DVec3,
    up: DVec3,
    forward: DVec3,
    perspective: bool,
    /// Screen = (projected - offset) * scale, y flipped.
    offset: [f64; 2],
    scale: f64,
    size: f64,
}

impl Camera {
    fn new(scene: &Scene, view: View, projection: Projection, size: f64) -> Self {
        let d = view.eye_direction();
        let world_up = if d.z.abs() > 0.99 { DVec3::Y } else { DVec3::Z };
        let forward = -d;
        let right = forward.cross(world_up).normalize();
        let up = right.cross(forward);
        let (eye, perspective) = match projection {
            Projection::Perspective { fov_y_deg } => {
                let distance = scene.radius / (fov_y_deg.to_radians() / 2.0).sin();
                (scene.centre + d * distance.max(scene.radius * 1.01), true)
            }
            Projection::Orthographic => (scene.centre + d * (scene.radius * 2.0), false),
        };
        let mut camera = Camera {
            eye,
            right,
            up,
            forward,
            perspective,
            offset: [0.0; 2],
            scale: 1.0,
            size,
        };
        // Frame on the projected extent of everything drawn, with a margin.
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        let points = scene
            .mesh
            .points()
            .chain(scene.ghost.iter().flat_map(|g| g.points()))
            .chain(scene.lines.iter().flat_map(|l| l.iter().copied()));
        for p in points {
            let q = camera.project_plane(p);
            for k in 0..2 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        if lo[0] <= hi[0] {
            let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-9);
            camera.scale = size * 0.9 / extent;
            camera.offset = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
        }
        camera
    }

    fn project_plane(&self, p: DVec3) -> [f64; 2] {
        let v = p - self.eye;
        let (x, y) = (v.dot(self.right), v.dot(self.up));
        if self.perspective {
            let z = v.dot(self.forward);
            [x / z, y / z]
        } else {
            [x, y]
        }
    }

    /// (screen x, screen y, depth key).
    fn project(&self, p: DVec3) -> DVec3 {
        let v = p - self.eye;
        let z = v.dot(self.forward);
        let q = self.project_plane(p);
        let depth = if self.perspective { 1.0 / z } else { -z };
        DVec3::new(
            (q[0] - self.offset[0]) * self.scale + self.size / 2.0,
            self.size / 2.0 - (q[1] - self.offset[1]) * self.scale,
            depth,
        )
    }

    /// Unit vector from `p` towards the eye.
    fn to_eye(&self, p: DVec3) -> DVec3 {
        if self.perspective {
            (self.eye - p).normalize_or_zero()
        } else {
            -self.forward
        }
    }
}

fn srgb_to_linear(c: u8) -> f32 {
    let c = c as f32 / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn linear_to_srgb(c: f32) -> u8 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

fn linear(c: [u8; 3]) -> [f32; 3] {
    c.map(srgb_to_linear)
}

/// Colour and depth buffers of one tile at the supersampled resolution.
struct Buffers {
    size: usize,
    depth: Vec<f64>,
    colour: Vec<[f32; 3]>,
}

impl Buffers {
    fn new(size: usize) -> Self {
        Buffers {
            size,
            depth: vec![f64::NEG_INFINITY; size * size],
            colour: vec![[0.0; 3]; size * size],
        }
    }
}

struct Lights {
    key: DVec3,
    fill: DVec3,
}

/// Rasterises a surface with per-pixel shading into `buffers`.
fn rasterise(
    surface: &Surface,
    camera: &Camera,
    lights: &Lights,
    front: [f32; 3],
    back: [f32; 3],
    buffers: &mut Buffers,
) {
    let size = buffers.size;
    for (k, (corners, normals)) in surface.triangles.iter().enumerate() {
        let corner_colours = surface.corner_colours.as_ref().map(|c| c[k]);
        let s = corners.map(|p| camera.project(p));
        let area = (s[1].x - s[0].x) * (s[2].y - s[0].y) - (s[1].y - s[0].y) * (s[2].x - s[0].x);
        if area.abs() < 1e-12 || !area.is_finite() {
            continue;
        }
        let min_x = s
            .iter()
            .map(|p| p.x)
            .fold(f64::INFINITY, f64::min)
            .floor()
            .max(0.0);
        let max_x = s
            .iter()
            .map(|p| p.x)
            .fold(f64::NEG_INFINITY, f64::max)
            .ceil()
            .min(size as f64 - 1.0);
        let min_y = s
            .iter()
            .map(|p| p.y)
            .fold(f64::INFINITY, f64::min)
            .floor()
            .max(0.0);
        let max_y = s
            .iter()
            .map(|p| p.y)
            .fold(f64::NEG_INFINITY, f64::max)
            .ceil()
            .min(size as f64 - 1.0);
        if min_x > max_x || min_y > max_y {
            continue;
        }
        let face = (corners[1] - corners[0]).cross(corners[2] - corners[0]);
        let facing = face.dot(camera.to_eye(corners[0])) >= 0.0;
        let base = if facing { front } else { back };
        let sign = if facing { 1.0 } else { -1.0 };
        let inv_area = 1.0 / area;
        for y in min_y as usize..=max_y as usize {
            let py = y as f64 + 0.5;
            for x in min_x as usize..=max_x as usize {
                let px = x as f64 + 0.5;
                let w0 = ((s[1].x - px) * (s[2].y - py) - (s[1].y - py) * (s[2].x - px)) * inv_area;
                let w1 = ((s[2].x - px) * (s[0].y - py) - (s[2].y - py) * (s[0].x - px)) * inv_area;
                let w2 = 1.0 - w0 - w1;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let depth = w0 * s[0].z + w1 * s[1].z + w2 * s[2].z;
                let i = y * size + x;
                if depth <= buffers.depth[i] {
                    continue;
                }
                buffers.depth[i] = depth;
                let n = (normals[0] * w0 + normals[1] * w1 + normals[2] * w2).normalize_or_zero()
                    * sign;
                let p = corners[0] * w0 + corners[1] * w1 + corners[2] * w2;
                let base = match corner_colours {
                    Some(c) => {
                        let dim = if facing { 1.0 } else { BACK_FACE_SHADE };
                        let w = [w0 as f32, w1 as f32, w2 as f32];
                        std::array::from_fn(|k| {
                            dim * (w[0] * c[0][k] + w[1] * c[1][k] + w[2] * c[2][k])
                        })
                    }
                    None => base,
                };
                buffers.colour[i] = shade(n, camera.to_eye(p), lights, base);
            }
        }
    }
}

fn shade(n: DVec3, to_eye: DVec3, lights: &Lights, base: [f32; 3]) -> [f32; 3] {
    let diffuse = 0.78 * n.dot(lights.key).max(0.0) + 0.3 * n.dot(lights.fill).max(0.0);
    // A little light from the viewer so faces seen edge-on are not black.
    let ambient = 0.06 + 0.1 * n.dot(to_eye).max(0.0);
    let half = (lights.key + to_eye).normalize_or_zero();
    let specular = 0.22 * n.dot(half).max(0.0).powi(48);
    let k = (ambient + diffuse) as f32;
    base.map(|c| c * k + specular as f32)
}

fn render_tile(scene: &Scene, view: View, tile: u32, options: &RenderOptions) -> Vec<u8> {
    let ss = options.supersample as usize;
    let size = tile as usize * ss;
    let camera = Camera::new(scene, view, options.projection, size as f64);
    // Key light from the upper left, fill from the right, both mostly from the viewer's side.
    let lights = Lights {
        key: (-camera.right * 0.45 + camera.up * 0.6 - camera.forward * 0.65).normalize(),
        fill: (camera.right * 0.7 - camera.up * 0.15 - camera.forward * 0.7).normalize(),
    };
    let mut main = Buffers::new(size);
    let (top, bottom) = (
        linear(options.background_top),
        linear(options.background_bottom),
    );
    for y in 0..size {
        let t = y as f32 / (size.max(2) - 1) as f32;
        let c: [f32; 3] = std::array::from_fn(|k| top[k] * (1.0 - t) + bottom[k] * t);
        main.colour[y * size..(y + 1) * size].fill(c);
    }
    if !scene.empty {
        rasterise(
            &scene.mesh,
            &camera,
            &lights,
            linear(options.mesh_colour),
            linear(options.back_colour),
            &mut main,
        );
        if let Some(ghost) = &scene.ghost {
            let mut g = Buffers::new(size);
            let ghost_colour = linear(options.ghost_colour);
            rasterise(ghost, &camera, &lights, ghost_colour, ghost_colour, &mut g);
            let alpha = options.ghost_opacity as f32;
            // Tolerance so a ghost coinciding with the mesh does not flicker through it.
            let eps = depth_tolerance(&camera, scene);
            for i in 0..size * size {
                if g.depth[i] > main.depth[i] + eps {
                    let (m, c) = (&mut main.colour[i], g.colour[i]);
                    *m = std::array::from_fn(|k| m[k] * (1.0 - alpha) + c[k] * alpha);
                }
            }
        }
        let eps = depth_tolerance(&camera, scene);
        let line_colour = linear(options.overlay_colour);
        for line in &scene.lines {
            draw_line(&mut main, &camera, *line, line_colour, ss, eps);
        }
    }
    if options.axes {
        draw_axes(&mut main, &camera, ss);
    }
    // Box-filter down to the tile and encode.
    let mut out = vec![0u8; tile as usize * tile as usize * 3];
    let norm = 1.0 / (ss * ss) as f32;
    for y in 0..tile as usize {
        for x in 0..tile as usize {
            let mut sum = [0f32; 3];
            for dy in 0..ss {
                for dx in 0..ss {
                    let c = main.colour[(y * ss + dy) * size + x * ss + dx];
                    for k in 0..3 {
                        sum[k] += c[k];
                    }
                }
            }
            let o = 3 * (y * tile as usize + x);
            for k in 0..3 {
                out[o + k] = linear_to_srgb(sum[k] * norm);
            }
        }
    }
    out
}

/// Depth-key difference equivalent to ~0.2% of the scene size at its centre.
fn depth_tolerance(camera: &Camera, scene: &Scene) -> f64 {
    let z = (scene.centre - camera.eye).dot(camera.forward);
    let dz = 0.002 * scene.radius;
    if camera.perspective {
        1.0 / (z - dz) - 1.0 / z
    } else {
        dz
    }
}

fn blend(buffers: &mut Buffers, x: i64, y: i64, colour: [f32; 3], alpha: f32) {
    let size = buffers.size as i64;
    if x < 0 || y < 0 || x >= size || y >= size {
        return;
    }
    let c = &mut buffers.colour[(y * size + x) as usize];
    *c = std::array::from_fn(|k| c[k] * (1.0 - alpha) + colour[k] * alpha);
}

/// A 3D segment, about one output pixel wide: opaque where in front of the surface, faint behind it.
fn draw_line(
    buffers: &mut Buffers,
    camera: &Camera,
    line: [DVec3; 2],
    colour: [f32; 3],
    ss: usize,
    eps: f64,
) {
    let (a, b) = (camera.project(line[0]), camera.project(line[1]));
    let steps = (b.x - a.x)
        .abs()
        .max((b.y - a.y).abs())
        .ceil()
        .clamp(1.0, 1e5) as usize;
    let width = ss.max(1) as i64;
    let size = buffers.size as i64;
    for k in 0..=steps {
        let t = k as f64 / steps as f64;
        let p = a + (b - a) * t;
        let (cx, cy) = (p.x.floor() as i64, p.y.floor() as i64);
        for dy in 0..width {
            for dx in 0..width {
                let (x, y) = (cx + dx - width / 2, cy + dy - width / 2);
                if x < 0 || y < 0 || x >= size || y >= size {
                    continue;
                }
                let visible = p.z + eps >= buffers.depth[(y * size + x) as usize];
                blend(buffers, x, y, colour, if visible { 0.9 } else { 0.25 });
            }
        }
    }
}

/// World axes from the tile's lower-left corner, drawn in 2D (no depth test).
fn draw_axes(buffers: &mut Buffers, camera: &Camera, ss: usize) {
    let size = buffers.size as f64;
    let origin = [size * 0.09, size * 0.91];
    let length = size * 0.06;
    let axes = [
        (DVec3::X, [0.8f32, 0.05, 0.04]),
        (DVec3::Y, [0.08, 0.6, 0.08]),
        (DVec3::Z, [0.1, 0.25, 0.9]),
    ];
    let width = ss.max(1) as i64;
    for (axis, colour) in axes {
        let d = [axis.dot(camera.right), -axis.dot(camera.up)];
        let steps = (length * 1.5) as usize;
        for k in 0..=steps {
            let t = k as f64 / steps as f64 * length;
            let (x, y) = (origin[0] + d[0] * t, origin[1] + d[1] * t);
            for dy in 0..width {
                for dx in 0..width {
                    blend(buffers, x as i64 + dx, y as i64 + dy, colour, 1.0);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::shapes::{icosphere, torus};

    /// The key to the error map's colours: the ramp end to end, labelled in mm.
    #[test]
    fn the_distance_colour_bar_is_the_ramp_labelled_in_mm() {
        use crate::metrics::distance_colour;
        let bar = distance_colour_bar(0.6);
        assert_eq!(bar.colours.first(), Some(&distance_colour(0.0, 0.6)));
        assert_eq!(bar.colours.last(), Some(&distance_colour(0.6, 0.6)));
        let labels: Vec<&str> = bar.labels.iter().map(|(_, l)| l.as_str()).collect();
        assert_eq!(labels, ["0", "0.3", "0.6 mm"]);
    }

    fn small() -> RenderOptions {
        RenderOptions {
            size_px: 160,
            ..Default::default()
        }
    }

    #[test]
    fn sphere_fills_the_centre_of_every_tile_and_leaves_corners_background() {
        let sphere = icosphere(DVec3::new(5.0, -3.0, 2.0), 10.0, 3);
        let options = small();
        let image = render_views(&sphere, &options).unwrap();
        assert_eq!((image.width, image.height), (160, 160));
        let background = |y: u32| {
            let t = (y * 2) as f32 / (160 - 1) as f32;
            let (a, b) = (
                linear(options.background_top),
                linear(options.background_bottom),
            );
            std::array::from_fn::<u8, 3, _>(|k| linear_to_srgb(a[k] * (1.0 - t) + b[k] * t))
        };
        for (tx, ty) in [(0, 0), (80, 0), (0, 80), (80, 80)] {
            // Centre: lit sphere, warm (red above blue) like the mesh colour.
            let c = image.pixel(tx + 40, ty + 40);
            assert!(c[0] > 100 && c[0] > c[2], "{c:?}");
            // Top-right corner (away from the axes): background gradient.
            let corner = image.pixel(tx + 77, ty + 2);
            let expected = background(2);
            assert!(
                corner.iter().zip(expected).all(|(a, b)| a.abs_diff(b) <= 2),
                "{corner:?} {expected:?}"
            );
        }
        // Framing: the sphere spans ~90% of a tile; a pixel just inside that span is mesh, just outside
        // is background (row through the centre of the front view).
        let row: Vec<bool> = (0..80).map(|x| image.pixel(x, 40)[0] > 90).collect();
        let first = row.iter().position(|&b| b).unwrap();
        let last = row.iter().rposition(|&b| b).unwrap();
        assert!(
            (2..=7).contains(&first) && (72..=77).contains(&last),
            "{first} {last}"
        );
    }

    #[test]
    fn rendering_is_deterministic_and_thread_independent() {
        let t = torus(10.0, 3.0, 48, 24);
        let options = RenderOptions {
            overlay_lines: vec![[DVec3::new(-15.0, 0.0, 0.0), DVec3::new(15.0, 0.0, 0.0)]],
            ghost: Some(icosphere(DVec3::ZERO, 8.0, 2)),
            ..small()
        };
        let run = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| encode_png(&render_views(&t, &options).unwrap()).unwrap())
        };
        assert_eq!(run(1), run(4));
    }

    #[test]
    fn overlay_lines_and_ghost_change_the_picture_where_expected() {
        let sphere = icosphere(DVec3::ZERO, 10.0, 3);
        let plain = render_views(&sphere, &small()).unwrap();
        // A vertical segment in front of the sphere (towards the front camera at -y).
        let with_line = RenderOptions {
            overlay_lines: vec![[DVec3::new(0.0, -10.5, -5.0), DVec3::new(0.0, -10.5, 5.0)]],
            ..small()
        };
        let lined = render_views(&sphere, &with_line).unwrap();
        let c = lined.pixel(40, 40);
        assert!(c[0] > 200 && c[1] > 150 && c[2] < 120, "line colour {c:?}");
        assert_ne!(plain.pixel(40, 40), c);
        // A ghost sphere around it (larger): the mesh shows through, tinted blue.
        let with_ghost = RenderOptions {
            ghost: Some(icosphere(DVec3::ZERO, 10.5, 3)),
            ..small()
        };
        let ghosted = render_views(&sphere, &with_ghost).unwrap();
        let (p, g) = (plain.pixel(40, 40), ghosted.pixel(40, 40));
        assert!(g[2] > p[2] && g[0] < p[0], "{p:?} -> {g:?}");
    }

    #[test]
    fn open_surfaces_show_their_back_in_the_back_colour_and_bad_options_fail() {
        // A single square facing +z, seen from the top (front side) and from below (back side).
        let square = Mesh {
            vertices: vec![DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y],
            normals: vec![],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        };
        let from = |elevation_deg| RenderOptions {
            views: vec![View {
                azimuth_deg: 0.0,
                elevation_deg,
            }],
            projection: Projection::Orthographic,
            axes: false,
            ..small()
        };
        let top = render_views(&square, &from(90.0)).unwrap().pixel(80, 80);
        let bottom = render_views(&square, &from(-90.0)).unwrap().pixel(80, 80);
        assert!(top[0] > top[2], "front is warm {top:?}");
        assert!(bottom[2] > bottom[0], "back is cool {bottom:?}");

        for bad in [
            RenderOptions {
                size_px: 0,
                ..small()
            },
            RenderOptions {
                views: vec![],
                ..small()
            },
            RenderOptions {
                supersample: 9,
                ..small()
            },
            RenderOptions {
                size_px: 8192,
                supersample: 4,
                ..small()
            },
            RenderOptions {
                projection: Projection::Perspective {
                    fov_y_deg: f64::NAN,
                },
                ..small()
            },
        ] {
            assert!(render_views(&square, &bad).is_err());
        }
        // An empty mesh renders the background only.
        let empty = render_views(&Mesh::default(), &small()).unwrap();
        assert_eq!(empty.width, 160);
    }

    #[test]
    fn vertex_colours_paint_both_sides_and_must_match_the_vertices() {
        // The square of the test above, its left edge green and its right edge red.
        let square = Mesh {
            vertices: vec![DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y],
            normals: vec![],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        };
        let (green, red) = ([0, 200, 0], [200, 0, 0]);
        let from = |elevation_deg, colours: Vec<[u8; 3]>| RenderOptions {
            views: vec![View {
                azimuth_deg: 0.0,
                elevation_deg,
            }],
            projection: Projection::Orthographic,
            axes: false,
            vertex_colours: Some(colours),
            ..small()
        };
        let colours = vec![green, red, red, green];
        let top = render_views(&square, &from(90.0, colours.clone())).unwrap();
        let bottom = render_views(&square, &from(-90.0, colours.clone())).unwrap();
        // Find the square's left and right thirds on the picture: the green end and the red end.
        let row = 80;
        let lit: Vec<u32> = (0..160)
            .filter(|&x| {
                let p = top.pixel(x, row);
                p[0].max(p[1]) > 60 && p[2] < 40
            })
            .collect();
        assert!(lit.len() > 40, "{lit:?}");
        let (a, b) = (top.pixel(lit[3], row), top.pixel(lit[lit.len() - 4], row));
        let (g_end, r_end) = if a[1] > a[0] { (a, b) } else { (b, a) };
        assert!(
            g_end[1] > 2 * g_end[0] && r_end[0] > 2 * r_end[1],
            "{g_end:?} {r_end:?}"
        );
        // From below, the same colours, darker; not the back colour.
        let (front, back) = (top.pixel(80, 80), bottom.pixel(80, 80));
        assert!(back[2] < 40, "the back is the vertex colour {back:?}");
        let sum = |p: [u8; 3]| p.iter().map(|&c| c as u32).sum::<u32>();
        assert!(sum(back) < sum(front), "{back:?} {front:?}");

        let short = RenderOptions {
            vertex_colours: Some(vec![red; 3]),
            ..small()
        };
        let err = render_views(&square, &short).unwrap_err().to_string();
        assert!(err.contains("3 vertex colours for 4 vertices"), "{err}");
    }

    #[test]
    fn a_colour_bar_is_drawn_under_the_views_with_its_labels() {
        let (blue, red) = ([0, 0, 255], [255, 0, 0]);
        let bar = ColourBar {
            colours: vec![blue, red],
            labels: vec![(0.0, "0".into()), (1.0, "1 mm".into())],
        };
        let ball = icosphere(DVec3::ZERO, 10.0, 2);
        let plain = render_views(&ball, &small()).unwrap();
        let keyed = render_views(
            &ball,
            &RenderOptions {
                colour_bar: Some(bar),
                ..small()
            },
        )
        .unwrap();
        // 160 px wide: one font pixel per pixel, a strip of 24 rows; the views above are unchanged.
        assert_eq!((keyed.width, keyed.height), (160, plain.height + 24));
        assert_eq!(keyed.pixels[..plain.pixels.len()], plain.pixels[..]);
        let y = plain.height + 6;
        assert_eq!(keyed.pixel(16, y), blue, "left end");
        assert_eq!(keyed.pixel(143, y), red, "right end");
        assert_eq!(keyed.pixel(5, y), [18, 20, 26], "margin");
        // Label text (light grey) under each end, none in the middle.
        let text_in = |x0: u32, x1: u32| {
            (x0..x1)
                .flat_map(|x| (plain.height + 14..plain.height + 21).map(move |y| (x, y)))
                .filter(|&(x, y)| keyed.pixel(x, y) == [220, 224, 232])
                .count()
        };
        assert!(
            text_in(10, 25) > 5 && text_in(125, 160) > 20,
            "labels drawn"
        );
        assert_eq!(text_in(40, 110), 0);
    }

    #[test]
    fn png_round_trips_through_the_decoder() {
        let image = render_views(&icosphere(DVec3::ZERO, 1.0, 1), &small()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.png");
        write_png(&path, &image).unwrap();
        let decoder = png::Decoder::new(std::fs::File::open(&path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (160, 160));
        assert_eq!(&buf[..info.buffer_size()], image.pixels.as_slice());
    }
}
