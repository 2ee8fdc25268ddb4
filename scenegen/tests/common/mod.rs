//! A tiny glTF writer for tests: accessors from slices, written as `.gltf` (data URI or an
//! external `.bin`) or `.glb`.

#![allow(dead_code)]

use std::path::Path;

use base64::Engine;
use serde_json::{json, Value};

#[derive(Default)]
pub struct Builder {
    pub bin: Vec<u8>,
    pub views: Vec<Value>,
    pub accessors: Vec<Value>,
}

fn type_name(n: usize) -> &'static str {
    match n {
        1 => "SCALAR",
        2 => "VEC2",
        3 => "VEC3",
        4 => "VEC4",
        16 => "MAT4",
        _ => panic!("unsupported component count {n}"),
    }
}

impl Builder {
    fn push_view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views
            .push(json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}));
        self.views.len() - 1
    }

    /// Float accessor of `n` components per element (with min / max).
    pub fn f32s(&mut self, data: &[f32], n: usize) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.push_view(&bytes);
        let mut lo = vec![f32::INFINITY; n];
        let mut hi = vec![f32::NEG_INFINITY; n];
        for e in data.chunks_exact(n) {
            for k in 0..n {
                lo[k] = lo[k].min(e[k]);
                hi[k] = hi[k].max(e[k]);
            }
        }
        self.accessors.push(json!({
            "bufferView": view, "componentType": 5126, "count": data.len() / n,
            "type": type_name(n), "min": lo, "max": hi
        }));
        self.accessors.len() - 1
    }

    /// Unsigned 16-bit accessor of `n` components per element.
    pub fn u16s(&mut self, data: &[u16], n: usize) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.push_view(&bytes);
        self.accessors.push(json!({
            "bufferView": view, "componentType": 5123, "count": data.len() / n,
            "type": type_name(n)
        }));
        self.accessors.len() - 1
    }

    /// The finished JSON with `rest` merged in and the buffer as a data URI.
    pub fn json(&self, rest: Value) -> Value {
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&self.bin)
        );
        self.json_with_uri(rest, Some(uri))
    }

    /// The JSON with the buffer at `uri` (`None`: the GLB binary chunk).
    pub fn json_with_uri(&self, rest: Value, uri: Option<String>) -> Value {
        let mut v = rest;
        let mut buffer = json!({"byteLength": self.bin.len()});
        if let Some(u) = uri {
            buffer["uri"] = json!(u);
        }
        v["asset"] = json!({"version": "2.0"});
        v["buffers"] = json!([buffer]);
        v["bufferViews"] = json!(self.views);
        v["accessors"] = json!(self.accessors);
        v
    }

    /// Writes `name.gltf` with an embedded buffer.
    pub fn write_gltf(&self, dir: &Path, name: &str, rest: Value) -> std::path::PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, serde_json::to_vec_pretty(&self.json(rest)).unwrap()).unwrap();
        path
    }

    /// The GLB bytes (JSON chunk + BIN chunk).
    pub fn glb(&self, rest: Value) -> Vec<u8> {
        let mut js = serde_json::to_vec(&self.json_with_uri(rest, None)).unwrap();
        while !js.len().is_multiple_of(4) {
            js.push(b' ');
        }
        let mut bin = self.bin.clone();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + js.len() + 8 + bin.len();
        let mut out = Vec::new();
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(js.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&js);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
        out
    }
}

/// Two joints (root at the origin, child at +Y 1), one skinned triangle with weights
/// (1, 0), (0.5, 0.5), (0, 1); the child rotates about Z from 0 to 90 degrees over 1 s (LINEAR).
pub fn skinned_model(b: &mut Builder) -> Value {
    let pos = b.f32s(&[1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 2.0, 0.0], 3);
    let joints = b.u16s(&[0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0], 4);
    let weights = b.f32s(&[1., 0., 0., 0., 0.5, 0.5, 0., 0., 0., 1., 0., 0.], 4);
    #[rustfmt::skip]
    let ibm = b.f32s(&[
        1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
        1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., -1., 0., 1.,
    ], 16);
    let h = std::f32::consts::FRAC_1_SQRT_2;
    let times = b.f32s(&[0.0, 1.0], 1);
    let rots = b.f32s(&[0., 0., 0., 1., 0., 0., h, h], 4);
    json!({
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"mesh": 0, "skin": 0},
            {"children": [2]},
            {"translation": [0.0, 1.0, 0.0]}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}}]}],
        "skins": [{"joints": [1, 2], "inverseBindMatrices": ibm}],
        "animations": [{
            "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}],
            "samplers": [{"input": times, "output": rots, "interpolation": "LINEAR"}]
        }]
    })
}

/// A unit quad in the glTF XY plane (facing +Z, i.e. -Y after the Z-up conversion... see the
/// tests) with UVs over [0, 1]^2, using material 0, plus an optional COLOR_0.
pub fn quad_mesh(b: &mut Builder, colors: bool) -> Value {
    let pos = b.f32s(&[-1., -1., 0., 1., -1., 0., 1., 1., 0., -1., 1., 0.], 3);
    let nrm = b.f32s(&[0., 0., 1., 0., 0., 1., 0., 0., 1., 0., 0., 1.], 3);
    // glTF UV: v = 0 at the top of the image; top of the quad (y = +1) gets v = 0.
    let uv = b.f32s(&[0., 1., 1., 1., 1., 0., 0., 0.], 2);
    let idx = b.u16s(&[0, 1, 2, 0, 2, 3], 1);
    let mut attrs = json!({"POSITION": pos, "NORMAL": nrm, "TEXCOORD_0": uv});
    if colors {
        let c = b.f32s(
            &[
                1., 0., 0., 1., 0., 1., 0., 1., 0., 0., 1., 1., 1., 1., 1., 1.,
            ],
            4,
        );
        attrs["COLOR_0"] = json!(c);
    }
    json!({"primitives": [{"attributes": attrs, "indices": idx, "material": 0}]})
}
