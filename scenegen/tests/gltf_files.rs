//! Loading hand-built glTF files: skinning, samplers through the loader, textures from external
//! files, vertex colours, .glb, and bad input that must fail with a clear error (never a panic).

mod common;

use std::path::Path;

use common::{quad_mesh, skinned_model, Builder};
use glam::{Mat4, Vec3};
use msth_core::Camera;
use msth_scenegen::scene::{self, Lighting, RenderOptions, Scene, Z_UP_FROM_Y_UP};
use msth_scenegen::texture::linear_to_srgb;
use msth_scenegen::{load, SceneGenError};
use serde_json::json;

fn posed(model: &msth_scenegen::Model, t: f32) -> Vec<scene::Triangle> {
    scene::posed_triangles(model, t, Mat4::IDENTITY, 0)
}

#[test]
fn skinning_with_two_joints_matches_hand_computed_positions() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = Builder::default();
    let rest = skinned_model(&mut b);
    let model = load(&b.write_gltf(dir.path(), "skin.gltf", rest)).unwrap();
    // Rest pose: the child joint is unrotated, so every vertex stays where it is.
    let t0 = posed(&model, 0.0);
    assert_eq!(t0.len(), 1);
    let p = t0[0].positions;
    assert!((p[0] - Vec3::new(1.0, 0.0, 0.0)).length() < 1e-6);
    assert!((p[1] - Vec3::new(1.0, 1.0, 1.0)).length() < 1e-6);
    assert!((p[2] - Vec3::new(1.0, 2.0, 0.0)).length() < 1e-6);
    // t = 1: the child turned 90 degrees about Z around (0, 1, 0).
    // v0 (joint 0 only) stays; v2 (joint 1): (1, 2, 0) -> (-1, 2, 0);
    // v1 half/half: 0.5 * (1, 1, 1) + 0.5 * (0, 2, 1) = (0.5, 1.5, 1).
    let p = posed(&model, 1.0)[0].positions;
    assert!((p[0] - Vec3::new(1.0, 0.0, 0.0)).length() < 1e-6, "{p:?}");
    assert!((p[1] - Vec3::new(0.5, 1.5, 1.0)).length() < 1e-6, "{p:?}");
    assert!((p[2] - Vec3::new(-1.0, 2.0, 0.0)).length() < 1e-6, "{p:?}");
    // t = 0.5: 45 degrees (slerp); v2 = (0, 1 + sqrt 2, 0).
    let p = posed(&model, 0.5)[0].positions;
    assert!(
        (p[2] - Vec3::new(0.0, 1.0 + 2f32.sqrt(), 0.0)).length() < 1e-5,
        "{p:?}"
    );
}

#[test]
fn step_and_cubic_samplers_through_the_loader() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    let times = b.f32s(&[0.0, 2.0], 1);
    let step_out = b.f32s(&[0., 0., 0., 5., 0., 0.], 3);
    // CUBICSPLINE scale: (a0, v0, b0, a1, v1, b1); v0 = 1, b0 = 1 (per second), v1 = 2, a1 = 0.
    let cubic_out = b.f32s(
        &[
            0., 0., 0., 1., 1., 1., 1., 1., 1., 0., 0., 0., 2., 2., 2., 0., 0., 0.,
        ],
        3,
    );
    let rest = json!({
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [mesh],
        "materials": [{}],
        "animations": [{
            "channels": [
                {"sampler": 0, "target": {"node": 0, "path": "translation"}},
                {"sampler": 1, "target": {"node": 0, "path": "scale"}}
            ],
            "samplers": [
                {"input": times, "output": step_out, "interpolation": "STEP"},
                {"input": times, "output": cubic_out, "interpolation": "CUBICSPLINE"}
            ]
        }]
    });
    let model = load(&b.write_gltf(dir.path(), "anim.gltf", rest)).unwrap();
    let a = model.animation.as_ref().unwrap();
    assert_eq!((a.start, a.end), (0.0, 2.0));
    // Vertex 0 is (-1, -1, 0): world = translation + scale * p.
    // t = 1 s: STEP keeps translation 0; cubic at u = 0.5 with dt = 2:
    // 1*0.5 + 2*1*0.125 + 2*0.5 + 0 = 1.75.
    let p = posed(&model, 1.0)[0].positions[0];
    assert!((p - Vec3::new(-1.75, -1.75, 0.0)).length() < 1e-5, "{p}");
    // t = 2 s: translation jumps to 5, scale 2.
    let p = posed(&model, 2.0)[0].positions[0];
    assert!((p - Vec3::new(3.0, -2.0, 0.0)).length() < 1e-5, "{p}");
}

fn write_png(path: &Path, w: u32, h: u32, px: &[[u8; 4]]) {
    let data: Vec<u8> = px.iter().flatten().copied().collect();
    image::RgbaImage::from_raw(w, h, data)
        .unwrap()
        .save(path)
        .unwrap();
}

/// Unlit lighting (albedo = displayed colour) and a camera at -Y looking at the origin.
fn unlit_scene(model: &msth_scenegen::Model) -> (Scene, Camera) {
    let scene = Scene {
        triangles: scene::posed_triangles(model, 0.0, Z_UP_FROM_Y_UP, 0),
        materials: scene::model_materials(model),
        lighting: Lighting {
            to_light: Vec3::Z,
            light: Vec3::ZERO,
            ambient_sky: Vec3::ONE,
            ambient_ground: Vec3::ONE,
        },
        background: None,
    };
    let cam = Camera::look_at(64, 64, 0.9, Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, Vec3::Z);
    (scene, cam)
}

fn pixel(img: &scene::RgbaImage8, u: f32, v: f32) -> [u8; 4] {
    let i = ((v as u32 * img.width + u as u32) * 4) as usize;
    img.data[i..i + 4].try_into().unwrap()
}

#[test]
fn external_bin_and_png_texture_with_nearest_filter() {
    let dir = tempfile::tempdir().unwrap();
    // 2x2: red, green / blue, white (row 0 = top = v 0).
    write_png(
        &dir.path().join("tex 1.png"),
        2,
        2,
        &[
            [255, 0, 0, 255],
            [0, 255, 0, 255],
            [0, 0, 255, 255],
            [255, 255, 255, 255],
        ],
    );
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    std::fs::write(dir.path().join("quad.bin"), &b.bin).unwrap();
    let rest = json!({
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [mesh],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"magFilter": 9728, "minFilter": 9728, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"uri": "tex%201.png"}]
    });
    let doc = b.json_with_uri(rest, Some("quad.bin".into()));
    let path = dir.path().join("quad.gltf");
    std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
    let model = load(&path).unwrap();
    let (scene, cam) = unlit_scene(&model);
    let img = scene::render(&scene, &cam, &RenderOptions::default());
    // glTF (x, y) -> world (x, 0, y) after the Z-up conversion: the quad's top-left quadrant
    // centre is world (-0.5, 0, 0.5).
    for (p, want) in [
        (Vec3::new(-0.5, 0.0, 0.5), [255, 0, 0, 255]),
        (Vec3::new(0.5, 0.0, 0.5), [0, 255, 0, 255]),
        (Vec3::new(-0.5, 0.0, -0.5), [0, 0, 255, 255]),
        (Vec3::new(0.5, 0.0, -0.5), [255, 255, 255, 255]),
    ] {
        let (u, v) = cam.project(p).unwrap();
        assert_eq!(pixel(&img, u, v), want, "at {p}");
    }
    // Outside the quad: transparent.
    assert_eq!(pixel(&img, 1.0, 1.0)[3], 0);
}

#[test]
fn base_colour_factor_lit_colour_at_projected_points() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    let rest = json!({
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [mesh],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.4, 0.2, 1.0]}}]
    });
    let model = load(&b.write_gltf(dir.path(), "lit.gltf", rest)).unwrap();
    let (mut scene, cam) = unlit_scene(&model);
    let light = Lighting::default();
    scene.lighting = light;
    let img = scene::render(&scene, &cam, &RenderOptions::default());
    // Normal (0, 0, 1) in glTF = (0, -1, 0) in the world; hemispheric ambient at n.z = 0.
    let n = Vec3::new(0.0, -1.0, 0.0);
    let shade = light.ambient_ground.lerp(light.ambient_sky, 0.5)
        + light.light * n.dot(light.to_light).max(0.0);
    let want = Vec3::new(0.8, 0.4, 0.2) * shade;
    for p in [
        Vec3::new(0.3, 0.0, 0.2),
        Vec3::new(-0.7, 0.0, -0.6),
        Vec3::ZERO,
    ] {
        let (u, v) = cam.project(p).unwrap();
        let got = pixel(&img, u, v);
        for c in 0..3 {
            let expected = (linear_to_srgb(want[c]) * 255.0 + 0.5) as i32;
            assert!((got[c] as i32 - expected).abs() <= 1, "{got:?} vs {want}");
        }
        assert_eq!(got[3], 255);
    }
}

#[test]
fn vertex_colours_are_interpolated() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, true);
    let rest = json!({
        "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}], "meshes": [mesh], "materials": [{}]
    });
    let model = load(&b.write_gltf(dir.path(), "vc.gltf", rest)).unwrap();
    let (scene, cam) = unlit_scene(&model);
    let img = scene::render(&scene, &cam, &RenderOptions::default());
    // Corners (glTF): (-1,-1) red, (1,-1) green, (1,1) blue; world (x, 0, y). Just inside each
    // corner the corner's colour dominates.
    for (p, channel) in [
        (Vec3::new(-0.9, 0.0, -0.95), 0),
        (Vec3::new(0.9, 0.0, -0.95), 1),
        (Vec3::new(0.95, 0.0, 0.9), 2),
    ] {
        let (u, v) = cam.project(p).unwrap();
        let px = pixel(&img, u, v);
        let max = (0..3).max_by_key(|&c| px[c]).unwrap();
        assert_eq!(max, channel, "{px:?} at {p}");
    }
}

#[test]
fn glb_loads_like_gltf() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = Builder::default();
    let rest = skinned_model(&mut b);
    let gltf = load(&b.write_gltf(dir.path(), "s.gltf", rest.clone())).unwrap();
    let glb_path = dir.path().join("s.glb");
    std::fs::write(&glb_path, b.glb(rest)).unwrap();
    let glb = load(&glb_path).unwrap();
    assert_eq!(posed(&gltf, 0.7), posed(&glb, 0.7));
}

fn expect_err(path: &Path, needles: &[&str]) -> SceneGenError {
    let e = load(path).expect_err("load should fail");
    let msg = e.to_string();
    for n in needles {
        assert!(msg.contains(n), "`{msg}` does not mention `{n}`");
    }
    assert!(
        msg.contains(&path.display().to_string()) || msg.contains(".bin") || msg.contains(".png"),
        "{msg}"
    );
    e
}

#[test]
fn bad_input_gives_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Missing file.
    expect_err(&d.join("nope.gltf"), &["nope.gltf", "No such file"]);
    // Not JSON.
    std::fs::write(d.join("junk.gltf"), b"{ not json").unwrap();
    expect_err(&d.join("junk.gltf"), &["not a valid glTF"]);
    // Truncated .glb.
    let mut b = Builder::default();
    let rest = skinned_model(&mut b);
    let glb = b.glb(rest.clone());
    std::fs::write(d.join("cut.glb"), &glb[..glb.len() / 2]).unwrap();
    expect_err(&d.join("cut.glb"), &["not a valid glTF"]);
    // No meshes.
    let b0 = Builder::default();
    let p = b0.write_gltf(
        d,
        "empty.gltf",
        json!({"scenes": [{"nodes": [0]}], "nodes": [{}]}),
    );
    expect_err(&p, &["no triangle meshes"]);
    // An animation accessor that claims more keyframes than its buffer view holds.
    let mut b = Builder::default();
    let mut rest = skinned_model(&mut b);
    let input = rest["animations"][0]["samplers"][0]["input"]
        .as_u64()
        .unwrap() as usize;
    b.accessors[input]["count"] = json!(1000);
    let p = b.write_gltf(d, "anim_range.gltf", rest.clone());
    expect_err(&p, &[&format!("accessor {input}"), "run past the end"]);
    // A vertex index out of range.
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    let idx = b.u16s(&[0, 1, 9], 1);
    let mut mesh = mesh;
    mesh["primitives"][0]["indices"] = json!(idx);
    let p = b.write_gltf(d, "idx.gltf", json!({"scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}], "meshes": [mesh], "materials": [{}]}));
    expect_err(&p, &["vertex index 9", "out of range"]);
    // A joint index beyond the skin's joints.
    let mut b = Builder::default();
    rest = skinned_model(&mut b);
    let j = rest["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"]
        .as_u64()
        .unwrap() as usize;
    let view = b.accessors[j]["bufferView"].as_u64().unwrap() as usize;
    let off = b.views[view]["byteOffset"].as_u64().unwrap() as usize;
    b.bin[off + 2] = 7; // joint 7 of 2
    let p = b.write_gltf(d, "joint.gltf", rest);
    expect_err(&p, &["JOINTS_0 value 7"]);
    // A missing external buffer.
    let b = Builder::default();
    let doc = b.json_with_uri(json!({}), Some("missing.bin".into()));
    std::fs::write(d.join("nobin.gltf"), serde_json::to_vec(&doc).unwrap()).unwrap();
    let e = load(&d.join("nobin.gltf")).unwrap_err();
    assert!(e.to_string().contains("missing.bin"), "{e}");
    // A node cycle.
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    let p = b.write_gltf(d, "cycle.gltf", json!({"scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "children": [1]}, {"children": [0]}], "meshes": [mesh], "materials": [{}]}));
    let e = load(&p).unwrap_err();
    assert!(e.to_string().contains("node"), "{e}");
}

#[test]
fn truncated_and_corrupted_files_never_panic() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = Builder::default();
    let rest = skinned_model(&mut b);
    let glb = b.glb(rest.clone());
    let path = dir.path().join("x.glb");
    for cut in (0..glb.len()).step_by(5) {
        std::fs::write(&path, &glb[..cut]).unwrap();
        let _ = load(&path);
    }
    // Flip bytes across the binary chunk (values, not structure): loads or fails cleanly, and
    // whatever loads can be posed.
    let mut seed = 1u64;
    for _ in 0..3000 {
        let mut g = glb.clone();
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let at = (seed >> 33) as usize % g.len();
        g[at] ^= (seed >> 13) as u8 | 1;
        std::fs::write(&path, &g).unwrap();
        if let Ok(m) = load(&path) {
            let _ = posed(&m, 0.5);
        }
    }
}
