//! Scenes in world space and their shading: triangles with attributes and materials, a
//! directional light plus hemispheric ambient (Lambert), and [`render`], which rasterises with
//! supersampling and resolves to an 8-bit straight-alpha RGBA image.
//!
//! Also builds the triangles of a [`Model`] posed at a time ([`posed_triangles`]: node
//! animation, skinning, glTF +Y up converted to this crate's +Z-up world) and fits a model into
//! a given sphere over its whole animation ([`Normalisation`]).

use std::sync::Arc;

use glam::{Mat4, Vec2, Vec3, Vec4};
use msth_core::Camera;

use crate::anim::{blend_matrix, joint_matrices, normal_matrix, world_matrices};
use crate::model::Model;
use crate::raster::{rasterize, RasterTriangle, EMPTY};
use crate::texture::{linear_to_srgb, Procedural, Texture};

/// glTF's +Y-up frame to the +Z-up world of the datasets (what Blender's importer does):
/// `(x, y, z) -> (x, -z, y)`.
pub const Z_UP_FROM_Y_UP: Mat4 = Mat4::from_cols(
    Vec4::new(1.0, 0.0, 0.0, 0.0),
    Vec4::new(0.0, 0.0, 1.0, 0.0),
    Vec4::new(0.0, -1.0, 0.0, 0.0),
    Vec4::new(0.0, 0.0, 0.0, 1.0),
);

/// A world-space triangle with shading attributes.
#[derive(Clone, Debug, PartialEq)]
pub struct Triangle {
    pub positions: [Vec3; 3],
    /// Unit normals per vertex (the face normal when the mesh has none).
    pub normals: [Vec3; 3],
    pub uvs: [Vec2; 3],
    /// Linear RGBA vertex colours (white when absent).
    pub colors: [Vec4; 3],
    /// Index into [`Scene::materials`].
    pub material: u32,
}

/// How a surface is coloured.
#[derive(Clone, Debug)]
pub struct SurfaceMaterial {
    /// Linear RGBA factor.
    pub base_color: Vec4,
    pub texture: Option<Arc<Texture>>,
    /// A solid texture of the world position (stage props), multiplied in.
    pub procedural: Option<Procedural>,
    pub double_sided: bool,
}

impl SurfaceMaterial {
    pub fn procedural(p: Procedural) -> Self {
        SurfaceMaterial {
            base_color: Vec4::ONE,
            texture: None,
            procedural: Some(p),
            double_sided: false,
        }
    }
}

/// One directional light and a hemispheric ambient term (sky colour for normals pointing up
/// (+Z), ground colour for normals pointing down).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    /// Unit vector towards the light.
    pub to_light: Vec3,
    /// Linear radiance scale of the light.
    pub light: Vec3,
    pub ambient_sky: Vec3,
    pub ambient_ground: Vec3,
}

impl Default for Lighting {
    fn default() -> Self {
        Lighting {
            to_light: Vec3::new(-0.45, -0.6, 0.8).normalize(),
            light: Vec3::splat(0.85),
            ambient_sky: Vec3::splat(0.38),
            ambient_ground: Vec3::splat(0.18),
        }
    }
}

/// Everything [`render`] needs.
#[derive(Clone, Debug)]
pub struct Scene {
    pub triangles: Vec<Triangle>,
    pub materials: Vec<SurfaceMaterial>,
    pub lighting: Lighting,
    /// Linear colour of empty pixels, or `None` for a transparent background.
    pub background: Option<Vec3>,
}

/// Settings of one render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderOptions {
    /// Samples per pixel along each axis (`supersample^2` per pixel, [`sample_pattern`]).
    pub supersample: u32,
    /// Near clipping distance.
    pub near: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            supersample: 6,
            near: 0.05,
        }
    }
}

/// An 8-bit sRGB image with straight (non-premultiplied) alpha, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbaImage8 {
    pub width: u32,
    pub height: u32,
    /// `width * height * 4` bytes.
    pub data: Vec<u8>,
}

impl RgbaImage8 {
    /// The image composited on white (`rgb * a + (1 - a)`, the D-NeRF convention) and its
    /// alpha channel (`None` when fully opaque).
    pub fn composite_on_white(&self) -> (msth_dataset::Image8, Option<Vec<u8>>) {
        let n = (self.width * self.height) as usize;
        let mut rgb = Vec::with_capacity(n * 3);
        let mut alpha = Vec::with_capacity(n);
        for px in self.data.chunks_exact(4) {
            let a = px[3] as f32 / 255.0;
            for c in &px[..3] {
                let v = *c as f32 / 255.0 * a + (1.0 - a);
                rgb.push((v * 255.0 + 0.5).clamp(0.0, 255.0) as u8);
            }
            alpha.push(px[3]);
        }
        let opaque = alpha.iter().all(|&a| a == 255);
        (
            msth_dataset::Image8 {
                width: self.width,
                height: self.height,
                data: rgb.into(),
            },
            (!opaque).then_some(alpha),
        )
    }
}

/// The linear colour of a visible surface point.
pub fn shade(scene: &Scene, tri: &Triangle, bary: Vec3, back_facing: bool) -> Vec3 {
    let m = &scene.materials[tri.material as usize];
    let p = tri.positions[0] * bary.x + tri.positions[1] * bary.y + tri.positions[2] * bary.z;
    let mut albedo = m.base_color;
    if let Some(t) = &m.texture {
        let uv = tri.uvs[0] * bary.x + tri.uvs[1] * bary.y + tri.uvs[2] * bary.z;
        albedo *= t.sample(uv.x, uv.y);
    }
    albedo *= tri.colors[0] * bary.x + tri.colors[1] * bary.y + tri.colors[2] * bary.z;
    let mut rgb = albedo.truncate();
    if let Some(pr) = &m.procedural {
        rgb *= pr.albedo(p);
    }
    let mut n = tri.normals[0] * bary.x + tri.normals[1] * bary.y + tri.normals[2] * bary.z;
    n = n.normalize_or_zero();
    if back_facing {
        n = -n;
    }
    let l = &scene.lighting;
    let hemi = 0.5 + 0.5 * n.z;
    let ambient = l.ambient_ground.lerp(l.ambient_sky, hemi);
    let diffuse = l.light * n.dot(l.to_light).max(0.0);
    rgb * (ambient + diffuse)
}

/// Sub-pixel sample positions of one pixel, `s^2` of them in `[0, 1)^2` (pixel corner at 0):
/// one sample in each cell of an `s x s` grid, shifted inside its cell so that the `s^2`
/// samples also have `s^2` distinct x and `s^2` distinct y coordinates (the canonical
/// arrangement of multi-jittered sampling, Kensler 2013). A regular grid gives an edge parallel
/// to an image axis (mortar lines, checker squares, the horizon) only `s + 1` coverage levels;
/// this pattern gives it `s^2 + 1`, at the same cost. `s = 1` is the pixel centre.
pub fn sample_pattern(s: u32) -> Vec<(f32, f32)> {
    let s = s.max(1);
    let n = s as f32;
    let mut out = Vec::with_capacity((s * s) as usize);
    for sy in 0..s {
        for sx in 0..s {
            out.push((
                (sx as f32 + (sy as f32 + 0.5) / n) / n,
                (sy as f32 + (sx as f32 + 0.5) / n) / n,
            ));
        }
    }
    out
}

/// Renders `scene` from `camera`: `supersample^2` samples per pixel at the positions of
/// [`sample_pattern`] (one rasterisation of the whole image per position, the camera's
/// principal point shifted by the sample's offset), the visible samples shaded and each
/// pixel's samples averaged in linear light (a box filter over the pixel, what the trainer's
/// rays jittered inside their pixel integrate), encoded as sRGB. With a transparent background,
/// alpha is the covered fraction and colour the mean of the covered samples (straight alpha).
pub fn render(scene: &Scene, camera: &Camera, opts: &RenderOptions) -> RgbaImage8 {
    let pattern = sample_pattern(opts.supersample);
    let raster = raster_triangles(scene);
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut sum = vec![Vec3::ZERO; w * h];
    let mut covered = vec![0u32; w * h];
    for &(ox, oy) in &pattern {
        // The rasteriser samples pixel centres (i + 0.5); shifting the principal point by
        // 0.5 - offset puts that sample at i + offset of `camera`'s pixel grid.
        let shifted = Camera {
            cx: camera.cx + 0.5 - ox,
            cy: camera.cy + 0.5 - oy,
            ..*camera
        };
        let frags = rasterize(&shifted, &raster, opts.near);
        for (k, f) in frags.iter().enumerate() {
            if f.tri == EMPTY {
                if let Some(bg) = scene.background {
                    sum[k] += bg;
                    covered[k] += 1;
                }
                continue;
            }
            let tri = &scene.triangles[f.tri as usize];
            sum[k] += shade(scene, tri, f.bary, f.back_facing);
            covered[k] += 1;
        }
    }
    let total = pattern.len() as f32;
    let mut data = Vec::with_capacity(w * h * 4);
    for (sum, &covered) in sum.iter().zip(&covered) {
        if covered == 0 {
            data.extend_from_slice(&[0, 0, 0, 0]);
            continue;
        }
        let mean = *sum / covered as f32;
        for c in mean.to_array() {
            data.push((linear_to_srgb(c) * 255.0 + 0.5) as u8);
        }
        data.push(((covered as f32 / total) * 255.0 + 0.5) as u8);
    }
    RgbaImage8 {
        width: camera.width,
        height: camera.height,
        data,
    }
}

/// The scene's triangles as the rasteriser takes them: single-sided materials cull back faces.
fn raster_triangles(scene: &Scene) -> Vec<RasterTriangle> {
    scene
        .triangles
        .iter()
        .map(|t| RasterTriangle {
            positions: t.positions,
            cull_back: !scene.materials[t.material as usize].double_sided,
        })
        .collect()
}

/// Depths (distance along the viewing axis) of every covered pixel centre, for near/far bounds.
pub fn depths(scene: &Scene, camera: &Camera, near: f32) -> Vec<f32> {
    let raster = raster_triangles(scene);
    rasterize(camera, &raster, near)
        .into_iter()
        .filter(|f| f.tri != EMPTY)
        .map(|f| f.depth)
        .collect()
}

/// The model's materials as [`SurfaceMaterial`]s, with the glTF default material appended last
/// (for primitives without one).
pub fn model_materials(model: &Model) -> Vec<SurfaceMaterial> {
    let mut out: Vec<SurfaceMaterial> = model
        .materials
        .iter()
        .map(|m| SurfaceMaterial {
            base_color: m.base_color,
            texture: m.texture.clone(),
            procedural: None,
            double_sided: m.double_sided,
        })
        .collect();
    out.push(SurfaceMaterial {
        base_color: Vec4::ONE,
        texture: None,
        procedural: None,
        double_sided: false,
    });
    out
}

/// The world-space triangles of `model` at `time_secs`: animated node transforms, skinning
/// (the skinned mesh's own node transform is ignored, as the glTF spec requires), then
/// `root_transform` above the scene roots. Material indices are those of [`model_materials`]
/// plus `material_offset`.
pub fn posed_triangles(
    model: &Model,
    time_secs: f32,
    root_transform: Mat4,
    material_offset: u32,
) -> Vec<Triangle> {
    let world = world_matrices(model, time_secs, root_transform);
    let default_material = model.materials.len() as u32 + material_offset;
    let mut out = Vec::new();
    for (node_index, node) in model.nodes.iter().enumerate() {
        let (Some(mesh), Some(node_world)) = (node.mesh, world[node_index]) else {
            continue;
        };
        // Skinned vertices land in the joints' world frame, which already includes the root
        // transform through the hierarchy.
        let joint_mats = node.skin.map(|s| joint_matrices(&model.skins[s], &world));
        for prim in &model.meshes[mesh].primitives {
            let n = prim.positions.len();
            let mut pos = Vec::with_capacity(n);
            let mut nrm = Vec::with_capacity(n);
            let node_normal = normal_matrix(&node_world);
            for v in 0..n {
                let m = match (&joint_mats, &prim.joints, &prim.weights) {
                    (Some(jm), Some(j), Some(w)) => blend_matrix(j[v], w[v], jm),
                    _ => None,
                };
                let (p, nn) = match m {
                    Some(m) => (
                        m.transform_point3(prim.positions[v]),
                        prim.normals
                            .as_ref()
                            .map(|ns| (normal_matrix(&m) * ns[v]).normalize_or_zero()),
                    ),
                    None => (
                        node_world.transform_point3(prim.positions[v]),
                        prim.normals
                            .as_ref()
                            .map(|ns| (node_normal * ns[v]).normalize_or_zero()),
                    ),
                };
                pos.push(p);
                nrm.push(nn);
            }
            // A mirroring node transform flips the winding (glTF 3.7.4).
            let mirrored =
                joint_mats.is_none() && glam::Mat3::from_mat4(node_world).determinant() < 0.0;
            let material = prim
                .material
                .map(|m| m as u32 + material_offset)
                .unwrap_or(default_material);
            for t in &prim.triangles {
                let mut idx = [t[0] as usize, t[1] as usize, t[2] as usize];
                if mirrored {
                    idx.swap(1, 2);
                }
                let positions = [pos[idx[0]], pos[idx[1]], pos[idx[2]]];
                let face = (positions[1] - positions[0])
                    .cross(positions[2] - positions[0])
                    .normalize_or_zero();
                let normals = idx.map(|i| match nrm[i] {
                    Some(v) if v != Vec3::ZERO => v,
                    _ => face,
                });
                let uvs = match &prim.uvs {
                    Some(uv) => idx.map(|i| uv[i]),
                    None => [Vec2::ZERO; 3],
                };
                let colors = match &prim.colors {
                    Some(c) => idx.map(|i| c[i]),
                    None => [Vec4::ONE; 3],
                };
                out.push(Triangle {
                    positions,
                    normals,
                    uvs,
                    colors,
                    material,
                });
            }
        }
    }
    out
}

/// A similarity transform placing the animated model in the world, computed over the whole
/// animation (every vertex at `samples` evenly spaced times).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Normalisation {
    /// Applied above the glTF scene roots: translate * scale * [`Z_UP_FROM_Y_UP`].
    pub root_transform: Mat4,
    pub scale: f32,
    pub translation: Vec3,
    /// Bounding box of the model over the animation, after the transform.
    pub bbox_min: Vec3,
    pub bbox_max: Vec3,
}

/// Where the normalised model goes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Placement {
    /// Bounding-box centre at the origin (object layout).
    Centred,
    /// Bounding-box centre above the origin, lowest point on z = 0 (stage layout).
    OnFloor,
}

impl Normalisation {
    /// Scales the model so that every vertex over the animation lies within `radius` of its
    /// bounding-box centre, then places it.
    pub fn fit(model: &Model, radius: f32, placement: Placement, samples: usize) -> Normalisation {
        let mut times: Vec<f32> = Vec::new();
        if let Some(a) = &model.animation {
            let n = samples.max(2);
            times.extend((0..n).map(|i| a.time_secs(i as f32 / (n - 1) as f32)));
        } else {
            times.push(0.0);
        }
        let mut all: Vec<Vec3> = Vec::new();
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for &t in &times {
            for tri in posed_triangles(model, t, Z_UP_FROM_Y_UP, 0) {
                for p in tri.positions {
                    lo = lo.min(p);
                    hi = hi.max(p);
                    all.push(p);
                }
            }
        }
        let centre = (lo + hi) * 0.5;
        let r = all
            .iter()
            .map(|p| (*p - centre).length())
            .fold(0.0f32, f32::max)
            .max(1e-6);
        let scale = radius / r;
        let translation = match placement {
            Placement::Centred => -centre * scale,
            Placement::OnFloor => Vec3::new(-centre.x * scale, -centre.y * scale, -lo.z * scale),
        };
        let root_transform = Mat4::from_translation(translation)
            * Mat4::from_scale(Vec3::splat(scale))
            * Z_UP_FROM_Y_UP;
        Normalisation {
            root_transform,
            scale,
            translation,
            bbox_min: lo * scale + translation,
            bbox_max: hi * scale + translation,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_pattern_has_one_sample_per_cell_and_per_axis_stratum() {
        assert_eq!(sample_pattern(1), vec![(0.5, 0.5)]);
        for s in 1..=16u32 {
            let p = sample_pattern(s);
            let n = (s * s) as usize;
            assert_eq!(p.len(), n);
            let mut cells = vec![0u32; n];
            let mut xs = vec![0u32; n];
            let mut ys = vec![0u32; n];
            for &(x, y) in &p {
                assert!(
                    (0.0..1.0).contains(&x) && (0.0..1.0).contains(&y),
                    "{s}: {x} {y}"
                );
                let (cx, cy) = ((x * s as f32) as usize, (y * s as f32) as usize);
                cells[cy * s as usize + cx] += 1;
                xs[(x * n as f32) as usize] += 1;
                ys[(y * n as f32) as usize] += 1;
            }
            assert!(cells.iter().all(|&c| c == 1), "{s}: cells {cells:?}");
            assert!(xs.iter().all(|&c| c == 1), "{s}: x strata {xs:?}");
            assert!(ys.iter().all(|&c| c == 1), "{s}: y strata {ys:?}");
        }
    }

    /// A quad at z = -1 in front of a camera at the origin looking down -Z, covering the image
    /// up to pixel coordinate `u_edge` (vertical edge) or `v_edge` (horizontal edge).
    fn half_plane(edge_u: Option<f32>, edge_v: Option<f32>) -> (Scene, Camera) {
        let cam = Camera {
            width: 8,
            height: 8,
            fx: 10.0,
            fy: 10.0,
            cx: 4.0,
            cy: 4.0,
            world_from_camera: Mat4::IDENTITY,
        };
        // u = cx + fx x / -z, v = cy - fy y / -z, at z = -1.
        let x1 = edge_u.map_or(10.0, |u| (u - cam.cx) / cam.fx);
        let y0 = edge_v.map_or(-10.0, |v| (cam.cy - v) / cam.fy);
        let (x0, y1) = (-10.0, 10.0);
        let corner = |x: f32, y: f32| Vec3::new(x, y, -1.0);
        let tri = |positions: [Vec3; 3]| Triangle {
            positions,
            normals: [Vec3::Z; 3],
            uvs: [Vec2::ZERO; 3],
            colors: [Vec4::ONE; 3],
            material: 0,
        };
        let scene = Scene {
            triangles: vec![
                tri([corner(x0, y0), corner(x1, y0), corner(x1, y1)]),
                tri([corner(x0, y0), corner(x1, y1), corner(x0, y1)]),
            ],
            materials: vec![SurfaceMaterial {
                base_color: Vec4::ONE,
                texture: None,
                procedural: None,
                double_sided: true,
            }],
            lighting: Lighting::default(),
            background: None,
        };
        (scene, cam)
    }

    /// Pixels an edge parallel to an image axis crosses get the covered fraction as alpha to
    /// within `1 / (2 s^2)` (and the 8-bit rounding), not the `1 / (2 s)` of a regular grid of
    /// samples: such edges (mortar lines, checker squares) are where a regular grid aliases.
    #[test]
    fn edges_parallel_to_the_axes_get_their_covered_fraction() {
        for s in [3u32, 6] {
            let tol = 0.5 / (s * s) as f32 + 1.0 / 255.0;
            for frac in [0.1f32, 0.3, 0.45, 0.7, 0.93] {
                for vertical in [true, false] {
                    let edge = 5.0 + frac;
                    let (scene, cam) = if vertical {
                        half_plane(Some(edge), None)
                    } else {
                        half_plane(None, Some(edge))
                    };
                    let img = render(
                        &scene,
                        &cam,
                        &RenderOptions {
                            supersample: s,
                            near: 0.05,
                        },
                    );
                    let alpha = |x: usize, y: usize| img.data[(y * 8 + x) * 4 + 3] as f32 / 255.0;
                    let (edge_px, inside, outside) = if vertical {
                        (alpha(5, 3), alpha(4, 3), alpha(6, 3))
                    } else {
                        (alpha(3, 5), alpha(3, 4), alpha(3, 6))
                    };
                    assert_eq!((inside, outside), (1.0, 0.0), "s {s}, frac {frac}");
                    assert!(
                        (edge_px - frac).abs() <= tol,
                        "s {s}, vertical {vertical}: covered fraction {frac}, alpha {edge_px}"
                    );
                }
            }
        }
    }
}
