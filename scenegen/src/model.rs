//! Loading a glTF 2.0 file (`.gltf` with embedded data URIs or external files next to it, or
//! binary `.glb`) into a plain [`Model`]: node hierarchy, triangle meshes, skins, materials with
//! decoded base-colour textures, and one animation.
//!
//! What is read: node TRS / matrix, mesh primitives of mode TRIANGLES, TRIANGLE_STRIP and
//! TRIANGLE_FAN (POSITION, NORMAL, TEXCOORD_n, COLOR_0, JOINTS_0, WEIGHTS_0, indices), skins
//! with inverse bind matrices, `pbrMetallicRoughness.baseColorFactor` and `baseColorTexture`
//! (any texcoord set, sampler wrap modes and magnification filter), `doubleSided`, and the
//! translation / rotation / scale channels of one animation. Ignored (reported in
//! [`Model::notes`]): points and lines, morph targets, cameras, other material inputs.
//!
//! Everything is validated here, so later stages (animation, skinning, rendering) can index
//! without checks: every vertex index, joint index and node reference is in range, every float
//! is finite.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use base64::Engine;
use glam::{Mat4, Quat, Vec2, Vec3, Vec4};
use gltf::mesh::Mode;

use crate::accessor::{read_floats, read_uints, Buffers};
use crate::anim::{Animation, Channel, Interpolation, Property, Sampler};
use crate::error::{Result, SceneGenError};
use crate::texture::{Filter, Texture, Wrap};

/// Largest file (document, buffer or image) that is read.
pub const MAX_FILE_BYTES: u64 = 1 << 30;
/// Largest texture side accepted.
pub const MAX_TEXTURE_SIDE: u32 = 8192;

/// A node's local transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LocalTransform {
    /// Translation, rotation, scale (`T * R * S`); these can be animated.
    Trs {
        translation: Vec3,
        rotation: Quat,
        scale: Vec3,
    },
    /// A fixed matrix (glTF forbids animating such nodes).
    Matrix(Mat4),
}

/// One node of the hierarchy.
#[derive(Clone, Debug)]
pub struct Node {
    pub name: Option<String>,
    /// Rest-pose local transform (animation overrides its TRS parts).
    pub local: LocalTransform,
    /// Child node indices (the hierarchy is a forest, checked on load).
    pub children: Vec<usize>,
    /// Index into [`Model::meshes`].
    pub mesh: Option<usize>,
    /// Index into [`Model::skins`].
    pub skin: Option<usize>,
}

/// A triangle list with per-vertex attributes (all the same length as `positions`).
#[derive(Clone, Debug, Default)]
pub struct Primitive {
    /// `POSITION`, in the mesh's local frame.
    pub positions: Vec<Vec3>,
    /// `NORMAL`, when present (flat face normals are used otherwise).
    pub normals: Option<Vec<Vec3>>,
    /// The texcoord set used by the material's base-colour texture, if any.
    pub uvs: Option<Vec<Vec2>>,
    /// `COLOR_0` as linear RGBA (RGB gets alpha 1).
    pub colors: Option<Vec<Vec4>>,
    /// `JOINTS_0`: indices into the node's skin joints (checked on load).
    pub joints: Option<Vec<[u16; 4]>>,
    /// `WEIGHTS_0` (normalised when skinning).
    pub weights: Option<Vec<Vec4>>,
    /// Three vertex indices per triangle, each `< positions.len()`.
    pub triangles: Vec<[u32; 3]>,
    /// Index into [`Model::materials`]; `None` = the glTF default material.
    pub material: Option<usize>,
}

/// A mesh: its primitives.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub name: Option<String>,
    pub primitives: Vec<Primitive>,
}

/// A skin: joint nodes and their inverse bind matrices (same length).
#[derive(Clone, Debug)]
pub struct Skin {
    /// Joint node indices.
    pub joints: Vec<usize>,
    /// One per joint (identity when the file has none).
    pub inverse_bind: Vec<Mat4>,
}

/// A material reduced to what the renderer uses.
#[derive(Clone, Debug)]
pub struct Material {
    pub name: Option<String>,
    /// Linear RGBA factor.
    pub base_color: Vec4,
    /// `baseColorTexture`, decoded.
    pub texture: Option<Arc<Texture>>,
    /// `doubleSided`: back faces are drawn (else culled).
    pub double_sided: bool,
}

impl Default for Material {
    /// The glTF default material: white, single-sided.
    fn default() -> Self {
        Material {
            name: None,
            base_color: Vec4::ONE,
            texture: None,
            double_sided: false,
        }
    }
}

/// A loaded model.
#[derive(Clone, Debug)]
pub struct Model {
    /// The file it was loaded from (for messages).
    pub source: PathBuf,
    pub nodes: Vec<Node>,
    /// Root nodes of the displayed scene.
    pub roots: Vec<usize>,
    pub meshes: Vec<Mesh>,
    pub skins: Vec<Skin>,
    pub materials: Vec<Material>,
    /// The played animation (the first of the file), if any.
    pub animation: Option<Animation>,
    /// Things of the file that were ignored, for the user.
    pub notes: Vec<String>,
}

fn invalid(path: &Path, what: impl Into<String>, message: impl Into<String>) -> SceneGenError {
    SceneGenError::Invalid {
        path: path.to_path_buf(),
        what: what.into(),
        message: message.into(),
    }
}

fn unsupported(path: &Path, what: impl Into<String>, message: impl Into<String>) -> SceneGenError {
    SceneGenError::Unsupported {
        path: path.to_path_buf(),
        what: what.into(),
        message: message.into(),
    }
}

/// Reads a whole file, refusing anything larger than [`MAX_FILE_BYTES`].
fn read_file(path: &Path) -> Result<Vec<u8>> {
    let meta = std::fs::metadata(path).map_err(SceneGenError::io(path))?;
    if meta.len() > MAX_FILE_BYTES {
        return Err(invalid(
            path,
            "file",
            format!(
                "{} bytes is more than the limit of {MAX_FILE_BYTES}",
                meta.len()
            ),
        ));
    }
    std::fs::read(path).map_err(SceneGenError::io(path))
}

/// Decodes `%XX` escapes of a relative URI.
fn percent_decode(uri: &str) -> String {
    let b = uri.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let Ok(v) = u8::from_str_radix(&uri[i + 1..i + 3], 16) {
                out.push(v);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The bytes a URI points to: a `data:` URI (base64) or a file relative to the document.
fn resolve_uri(doc_path: &Path, uri: &str, what: &str) -> Result<Vec<u8>> {
    if let Some(rest) = uri.strip_prefix("data:") {
        let (header, payload) = rest
            .split_once(',')
            .ok_or_else(|| invalid(doc_path, what, "data URI without a comma"))?;
        if !header.ends_with(";base64") {
            return Err(unsupported(
                doc_path,
                what,
                "data URIs that are not base64-encoded",
            ));
        }
        return base64::engine::general_purpose::STANDARD
            .decode(payload.trim())
            .map_err(|e| invalid(doc_path, what, format!("bad base64 in data URI: {e}")));
    }
    if uri.contains("://") {
        return Err(unsupported(
            doc_path,
            what,
            format!("remote URI `{uri}` (only data URIs and relative files)"),
        ));
    }
    let rel = percent_decode(uri);
    let dir = doc_path.parent().unwrap_or(Path::new("."));
    read_file(&dir.join(rel))
}

/// Loads a `.gltf` or `.glb` file. See the module docs for what is read.
pub fn load(path: &Path) -> Result<Model> {
    let bytes = read_file(path)?;
    // `parse` closes the validation gaps we know of; should the third-party parser still
    // panic on some input, that becomes an error about the file rather than a crash.
    let gltf = std::panic::catch_unwind(|| parse(path, &bytes)).unwrap_or_else(|_| {
        Err(SceneGenError::Format {
            path: path.to_path_buf(),
            message: "the glTF parser failed on this file (malformed content)".into(),
        })
    })?;
    let doc = &gltf.document;
    let mut notes = Vec::new();

    // Buffers.
    let mut buffers = Vec::new();
    for buffer in doc.buffers() {
        let what = format!("buffer {}", buffer.index());
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => gltf.blob.clone().ok_or_else(|| {
                invalid(
                    path,
                    &what,
                    "refers to the GLB binary chunk, which is missing",
                )
            })?,
            gltf::buffer::Source::Uri(uri) => resolve_uri(path, uri, &what)?,
        };
        if data.len() < buffer.length() {
            return Err(invalid(
                path,
                what,
                format!(
                    "holds {} bytes but byteLength says {}",
                    data.len(),
                    buffer.length()
                ),
            ));
        }
        buffers.push(data);
    }
    let buffers = Buffers(buffers);

    // Nodes.
    let mut nodes = Vec::new();
    for node in doc.nodes() {
        let local = match node.transform() {
            gltf::scene::Transform::Matrix { matrix } => {
                let m = Mat4::from_cols_array_2d(&matrix);
                if !m.is_finite() {
                    return Err(invalid(
                        path,
                        format!("node {}", node.index()),
                        "matrix is not finite",
                    ));
                }
                LocalTransform::Matrix(m)
            }
            gltf::scene::Transform::Decomposed {
                translation,
                rotation,
                scale,
            } => {
                let (t, r, s) = (
                    Vec3::from(translation),
                    Quat::from_array(rotation),
                    Vec3::from(scale),
                );
                if !(t.is_finite() && r.is_finite() && s.is_finite()) || r.length() < 1e-6 {
                    return Err(invalid(
                        path,
                        format!("node {}", node.index()),
                        "translation / rotation / scale not finite or zero rotation",
                    ));
                }
                LocalTransform::Trs {
                    translation: t,
                    rotation: r.normalize(),
                    scale: s,
                }
            }
        };
        if node.camera().is_some() {
            notes.push(format!("node {}: camera ignored", node.index()));
        }
        nodes.push(Node {
            name: node.name().map(str::to_string),
            local,
            children: node.children().map(|c| c.index()).collect(),
            mesh: node.mesh().map(|m| m.index()),
            skin: node.skin().map(|s| s.index()),
        });
    }
    check_hierarchy(path, &nodes)?;

    // Roots of the displayed scene.
    let scene = gltf.default_scene().or_else(|| doc.scenes().next());
    let roots: Vec<usize> = match scene {
        Some(s) => s.nodes().map(|n| n.index()).collect(),
        None => {
            let mut has_parent = vec![false; nodes.len()];
            for n in &nodes {
                for &c in &n.children {
                    has_parent[c] = true;
                }
            }
            (0..nodes.len()).filter(|&i| !has_parent[i]).collect()
        }
    };

    // Materials (textures decoded once per image).
    let mut images: Vec<Option<image::RgbaImage>> = vec![None; doc.images().count()];
    let mut materials = Vec::new();
    let mut texcoord_set = Vec::new();
    for m in doc.materials() {
        let what = format!("material {}", m.index().unwrap_or(0));
        let pbr = m.pbr_metallic_roughness();
        let base = Vec4::from(pbr.base_color_factor());
        if !base.is_finite() {
            return Err(invalid(path, what, "baseColorFactor is not finite"));
        }
        let mut texture = None;
        let mut set = 0;
        if let Some(info) = pbr.base_color_texture() {
            let tex = info.texture();
            let img = tex.source();
            let idx = img.index();
            if images[idx].is_none() {
                images[idx] = Some(decode_image(path, &img, &buffers)?);
            }
            let sampler = tex.sampler();
            let filter = match sampler.mag_filter() {
                Some(gltf::texture::MagFilter::Nearest) => Filter::Nearest,
                _ => Filter::Bilinear,
            };
            let rgba = images[idx].as_ref().expect("decoded above");
            texture = Some(Arc::new(Texture::from_rgba8(
                rgba,
                Wrap::from_gltf(sampler.wrap_s()),
                Wrap::from_gltf(sampler.wrap_t()),
                filter,
            )));
            set = info.tex_coord();
        }
        materials.push(Material {
            name: m.name().map(str::to_string),
            base_color: base,
            texture,
            double_sided: m.double_sided(),
        });
        texcoord_set.push(set);
    }

    // Meshes.
    let mut meshes = Vec::new();
    for mesh in doc.meshes() {
        let mut prims = Vec::new();
        for prim in mesh.primitives() {
            let what = format!("mesh {} primitive {}", mesh.index(), prim.index());
            let set = prim
                .material()
                .index()
                .map(|i| texcoord_set[i])
                .unwrap_or(0);
            match read_primitive(path, &what, &prim, &buffers, set)? {
                Some(p) => prims.push(p),
                None => notes.push(format!("{what}: mode {:?} ignored", prim.mode())),
            }
            if prim.morph_targets().next().is_some() {
                notes.push(format!("{what}: morph targets ignored"));
            }
        }
        meshes.push(Mesh {
            name: mesh.name().map(str::to_string),
            primitives: prims,
        });
    }
    if meshes.iter().all(|m| m.primitives.is_empty()) {
        return Err(invalid(
            path,
            "meshes",
            "the file has no triangle meshes to render",
        ));
    }

    // Skins.
    let mut skins = Vec::new();
    for skin in doc.skins() {
        let what = format!("skin {}", skin.index());
        let joints: Vec<usize> = skin.joints().map(|j| j.index()).collect();
        if joints.is_empty() {
            return Err(invalid(path, what, "has no joints"));
        }
        let inverse_bind = match skin.inverse_bind_matrices() {
            Some(acc) => {
                let v = read_floats(
                    path,
                    &acc,
                    &buffers,
                    16,
                    &format!("{what} inverseBindMatrices"),
                )?;
                if v.len() / 16 < joints.len() {
                    return Err(invalid(
                        path,
                        what,
                        format!(
                            "{} inverse bind matrices for {} joints",
                            v.len() / 16,
                            joints.len()
                        ),
                    ));
                }
                v.chunks_exact(16)
                    .take(joints.len())
                    .map(Mat4::from_cols_slice)
                    .collect()
            }
            None => vec![Mat4::IDENTITY; joints.len()],
        };
        skins.push(Skin {
            joints,
            inverse_bind,
        });
    }
    for (i, n) in nodes.iter().enumerate() {
        if let (Some(s), Some(m)) = (n.skin, n.mesh) {
            let n_joints = skins[s].joints.len();
            for p in &meshes[m].primitives {
                if let Some(j) = &p.joints {
                    if let Some(bad) = j.iter().flatten().find(|&&v| v as usize >= n_joints) {
                        return Err(invalid(
                            path,
                            format!("node {i} (mesh {m}, skin {s})"),
                            format!("JOINTS_0 value {bad} is out of range ({n_joints} joints)"),
                        ));
                    }
                }
            }
        }
    }

    // The first animation.
    let animation = match doc.animations().next() {
        Some(a) => {
            let (anim, skipped) = read_animation(path, &a, &buffers, &nodes)?;
            if skipped > 0 {
                notes.push(format!("{skipped} morph-target weight channels ignored"));
            }
            Some(anim)
        }
        None => None,
    };
    if doc.animations().count() > 1 {
        notes.push(format!(
            "{} animations in the file; playing the first",
            doc.animations().count()
        ));
    }

    Ok(Model {
        source: path.to_path_buf(),
        nodes,
        roots,
        meshes,
        skins,
        materials,
        animation,
        notes,
    })
}

/// Parses and validates the document. `gltf-json` 1.4's validation has gaps that end in panics
/// later (found by `truncated_and_corrupted_files_never_panic`): it indexes the accessor of every
/// `POSITION` attribute without a range check, and it does not check animation channel targets.
/// Those are checked first, on the unvalidated JSON.
fn parse(path: &Path, bytes: &[u8]) -> Result<gltf::Gltf> {
    let format = |message: String| SceneGenError::Format {
        path: path.to_path_buf(),
        message,
    };
    let raw =
        gltf::Gltf::from_slice_without_validation(bytes).map_err(|e| format(e.to_string()))?;
    let root = raw.document.into_json();
    let n_accessors = root.accessors.len();
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (k, prim) in mesh.primitives.iter().enumerate() {
            for (semantic, index) in &prim.attributes {
                if index.value() >= n_accessors {
                    return Err(format(format!(
                        "meshes[{m}].primitives[{k}].attributes.{semantic:?}: accessor {} does \
                         not exist ({n_accessors} accessors)",
                        index.value()
                    )));
                }
            }
        }
    }
    // Its animation validation skips the channels' targets, which the accessors then unwrap.
    let n_nodes = root.nodes.len();
    for (a, anim) in root.animations.iter().enumerate() {
        for (c, ch) in anim.channels.iter().enumerate() {
            if ch.target.node.value() >= n_nodes {
                return Err(format(format!(
                    "animations[{a}].channels[{c}].target.node: node {} does not exist \
                     ({n_nodes} nodes)",
                    ch.target.node.value()
                )));
            }
            if !matches!(ch.target.path, gltf::json::validation::Checked::Valid(_)) {
                return Err(format(format!(
                    "animations[{a}].channels[{c}].target.path: not one of translation, \
                     rotation, scale, weights"
                )));
            }
        }
    }
    let document = gltf::Document::from_json(root).map_err(|e| format(e.to_string()))?;
    Ok(gltf::Gltf {
        document,
        blob: raw.blob,
    })
}

/// Rejects node graphs that are not forests (cycles, shared children).
fn check_hierarchy(path: &Path, nodes: &[Node]) -> Result<()> {
    let mut parent = vec![None; nodes.len()];
    for (i, n) in nodes.iter().enumerate() {
        for &c in &n.children {
            if c == i {
                return Err(invalid(path, format!("node {i}"), "is its own child"));
            }
            if let Some(p) = parent[c] {
                return Err(invalid(
                    path,
                    format!("node {c}"),
                    format!("has two parents ({p} and {i})"),
                ));
            }
            parent[c] = Some(i);
        }
    }
    // With at most one parent each, a cycle is a chain of parents that never ends.
    for start in 0..nodes.len() {
        let mut at = start;
        let mut steps = 0;
        while let Some(p) = parent[at] {
            at = p;
            steps += 1;
            if steps > nodes.len() {
                return Err(invalid(
                    path,
                    format!("node {start}"),
                    "the node hierarchy has a cycle",
                ));
            }
        }
    }
    Ok(())
}

fn decode_image(path: &Path, img: &gltf::Image, buffers: &Buffers) -> Result<image::RgbaImage> {
    let what = format!("image {}", img.index());
    let bytes: Vec<u8> = match img.source() {
        gltf::image::Source::View { view, .. } => {
            let buf = buffers
                .0
                .get(view.buffer().index())
                .ok_or_else(|| invalid(path, &what, "its buffer is missing"))?;
            let end = view.offset().saturating_add(view.length());
            buf.get(view.offset()..end)
                .ok_or_else(|| invalid(path, &what, "its bufferView lies outside the buffer"))?
                .to_vec()
        }
        gltf::image::Source::Uri { uri, .. } => resolve_uri(path, uri, &what)?,
    };
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(SceneGenError::io(path))?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_TEXTURE_SIDE);
    limits.max_image_height = Some(MAX_TEXTURE_SIDE);
    reader.limits(limits);
    let decoded = reader
        .decode()
        .map_err(|e| invalid(path, &what, format!("cannot decode: {e}")))?;
    Ok(decoded.to_rgba8())
}

fn read_primitive(
    path: &Path,
    what: &str,
    prim: &gltf::Primitive,
    buffers: &Buffers,
    uv_set: u32,
) -> Result<Option<Primitive>> {
    let mode = prim.mode();
    if !matches!(
        mode,
        Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
    ) {
        return Ok(None);
    }
    let pos_acc = prim
        .get(&gltf::Semantic::Positions)
        .ok_or_else(|| invalid(path, what, "has no POSITION attribute"))?;
    let positions: Vec<Vec3> =
        read_floats(path, &pos_acc, buffers, 3, &format!("{what} POSITION"))?
            .chunks_exact(3)
            .map(Vec3::from_slice)
            .collect();
    let n = positions.len();
    let check_len = |len: usize, name: &str| -> Result<()> {
        if len != n {
            return Err(invalid(
                path,
                what,
                format!("{name} has {len} elements but POSITION has {n}"),
            ));
        }
        Ok(())
    };
    let normals = match prim.get(&gltf::Semantic::Normals) {
        Some(a) => {
            let v: Vec<Vec3> = read_floats(path, &a, buffers, 3, &format!("{what} NORMAL"))?
                .chunks_exact(3)
                .map(Vec3::from_slice)
                .collect();
            check_len(v.len(), "NORMAL")?;
            Some(v)
        }
        None => None,
    };
    let uvs = match prim.get(&gltf::Semantic::TexCoords(uv_set)) {
        Some(a) => {
            let v: Vec<Vec2> =
                read_floats(path, &a, buffers, 2, &format!("{what} TEXCOORD_{uv_set}"))?
                    .chunks_exact(2)
                    .map(Vec2::from_slice)
                    .collect();
            check_len(v.len(), "TEXCOORD")?;
            Some(v)
        }
        None => None,
    };
    let colors = match prim.get(&gltf::Semantic::Colors(0)) {
        Some(a) => {
            let k = a.dimensions().multiplicity();
            if k != 3 && k != 4 {
                return Err(invalid(path, what, "COLOR_0 must be VEC3 or VEC4"));
            }
            let raw = read_floats(path, &a, buffers, k, &format!("{what} COLOR_0"))?;
            let v: Vec<Vec4> = raw
                .chunks_exact(k)
                .map(|c| Vec4::new(c[0], c[1], c[2], if k == 4 { c[3] } else { 1.0 }))
                .collect();
            check_len(v.len(), "COLOR_0")?;
            Some(v)
        }
        None => None,
    };
    let joints = match prim.get(&gltf::Semantic::Joints(0)) {
        Some(a) => {
            let raw = read_uints(path, &a, buffers, 4, &format!("{what} JOINTS_0"))?;
            let v: Vec<[u16; 4]> = raw
                .chunks_exact(4)
                .map(|c| [c[0] as u16, c[1] as u16, c[2] as u16, c[3] as u16])
                .collect();
            check_len(v.len(), "JOINTS_0")?;
            Some(v)
        }
        None => None,
    };
    let weights = match prim.get(&gltf::Semantic::Weights(0)) {
        Some(a) => {
            let v: Vec<Vec4> = read_floats(path, &a, buffers, 4, &format!("{what} WEIGHTS_0"))?
                .chunks_exact(4)
                .map(Vec4::from_slice)
                .collect();
            check_len(v.len(), "WEIGHTS_0")?;
            Some(v)
        }
        None => None,
    };
    if joints.is_some() != weights.is_some() {
        return Err(invalid(
            path,
            what,
            "JOINTS_0 and WEIGHTS_0 must come together",
        ));
    }
    let indices: Vec<u32> = match prim.indices() {
        Some(a) => {
            let v = read_uints(path, &a, buffers, 1, &format!("{what} indices"))?;
            if let Some(bad) = v.iter().find(|&&i| i as usize >= n) {
                return Err(invalid(
                    path,
                    format!("{what} indices (accessor {})", a.index()),
                    format!("vertex index {bad} is out of range ({n} vertices)"),
                ));
            }
            v
        }
        None => (0..n as u32).collect(),
    };
    let triangles = assemble(mode, &indices);
    Ok(Some(Primitive {
        positions,
        normals,
        uvs,
        colors,
        joints,
        weights,
        triangles,
        material: prim.material().index(),
    }))
}

/// Triangles of a list, strip or fan (glTF 2.0 section 3.7.2.1 winding rules).
pub fn assemble(mode: Mode, idx: &[u32]) -> Vec<[u32; 3]> {
    match mode {
        Mode::Triangles => idx.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        Mode::TriangleStrip => (0..idx.len().saturating_sub(2))
            .map(|i| {
                if i % 2 == 0 {
                    [idx[i], idx[i + 1], idx[i + 2]]
                } else {
                    [idx[i + 1], idx[i], idx[i + 2]]
                }
            })
            .collect(),
        Mode::TriangleFan => (1..idx.len().saturating_sub(1))
            .map(|i| [idx[0], idx[i], idx[i + 1]])
            .collect(),
        _ => Vec::new(),
    }
}

fn read_animation(
    path: &Path,
    anim: &gltf::Animation,
    buffers: &Buffers,
    nodes: &[Node],
) -> Result<(Animation, usize)> {
    let mut channels = Vec::new();
    let mut notes_skipped = 0;
    for ch in anim.channels() {
        let target = ch.target();
        let node = target.node().index();
        let what = format!("animation {} channel {}", anim.index(), ch.index());
        let property = match target.property() {
            gltf::animation::Property::Translation => Property::Translation,
            gltf::animation::Property::Rotation => Property::Rotation,
            gltf::animation::Property::Scale => Property::Scale,
            gltf::animation::Property::MorphTargetWeights => {
                notes_skipped += 1;
                continue;
            }
        };
        if matches!(nodes[node].local, LocalTransform::Matrix(_)) {
            return Err(invalid(
                path,
                what,
                format!("animates node {node}, which has a matrix (glTF forbids this)"),
            ));
        }
        let s = ch.sampler();
        let interpolation = match s.interpolation() {
            gltf::animation::Interpolation::Linear => Interpolation::Linear,
            gltf::animation::Interpolation::Step => Interpolation::Step,
            gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
        };
        let input = read_floats(path, &s.input(), buffers, 1, &format!("{what} input"))?;
        let k = property.components();
        let output = read_floats(path, &s.output(), buffers, k, &format!("{what} output"))?;
        let sampler = Sampler::new(input, output, k, interpolation)
            .map_err(|m| invalid(path, &what, m.to_string()))?;
        channels.push(Channel {
            node,
            property,
            sampler,
        });
    }
    Ok((Animation::new(channels), notes_skipped))
}
