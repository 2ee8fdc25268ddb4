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
    /// Samples per pixel along each axis (`supersample^2` per pixel, a regular grid).
    pub supersample: u32,
    /// Near clipping distance.
    pub near: f32,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            supersample: 3,
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

/// Renders `scene` from `camera`: rasterise at `supersample` times the resolution, shade the
/// visible samples, average each pixel's samples in linear light, encode sRGB. With a
/// transparent background, alpha is the covered fraction and colour the mean of the covered
/// samples (straight alpha).
pub fn render(scene: &Scene, camera: &Camera, opts: &RenderOptions) -> RgbaImage8 {
    let s = opts.supersample.max(1);
    let fine = Camera {
        width: camera.width * s,
        height: camera.height * s,
        fx: camera.fx * s as f32,
        fy: camera.fy * s as f32,
        cx: camera.cx * s as f32,
        cy: camera.cy * s as f32,
        world_from_camera: camera.world_from_camera,
    };
    let raster = raster_triangles(scene);
    let frags = rasterize(&fine, &raster, opts.near);
    let (w, h) = (camera.width as usize, camera.height as usize);
    let fw = fine.width as usize;
    let mut data = Vec::with_capacity(w * h * 4);
    for y in 0..h {
        for x in 0..w {
            let mut sum = Vec3::ZERO;
            let mut covered = 0u32;
            for sy in 0..s as usize {
                for sx in 0..s as usize {
                    let f = frags[(y * s as usize + sy) * fw + x * s as usize + sx];
                    if f.tri == EMPTY {
                        if let Some(bg) = scene.background {
                            sum += bg;
                            covered += 1;
                        }
                        continue;
                    }
                    let tri = &scene.triangles[f.tri as usize];
                    sum += shade(scene, tri, f.bary, f.back_facing);
                    covered += 1;
                }
            }
            let total = s * s;
            if covered == 0 {
                data.extend_from_slice(&[0, 0, 0, 0]);
                continue;
            }
            let mean = sum / covered as f32;
            for c in mean.to_array() {
                data.push((linear_to_srgb(c) * 255.0 + 0.5) as u8);
            }
            data.push(((covered as f32 / total as f32) * 255.0 + 0.5) as u8);
        }
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
