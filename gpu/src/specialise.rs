//! Kernels specialised to one model (issue #17): the region of `render.wgsl` between its two
//! `specialise` lines, which holds the per-sample passes' encodings (`encode_field4`,
//! `encode_proposal4`), MLPs (`proposal_mlp4`, `density_mlp4`, `color_mlp4`) and geometry-feature
//! transfers (`geo_to_work`, `geo_from_work`), rewritten with the model's level values, MLP
//! weights and feature count as constants.
//!
//! # Why
//! The generic versions read each level's scale, strides and offset from the `Model` uniform at
//! an index that changes with the level, each weight from the `rest` storage buffer and each
//! activation from an indexed private array. A software adapter (SwiftShader in Chromium,
//! lavapipe) turns each such read into a per-lane gather, and a GPU keeps neither weights nor
//! indexed arrays in registers. A model's decoders are small (the presets' hold 6,000-9,500
//! weights) and the same in every frame and chunk of a file, so they fit in the shader's code:
//! - **encodings**: the level loop unrolled, each level's uniform row a literal `Level(...)`
//!   passed to `grid_level_at`, so the compiler folds the dense/hashed and 3D/4D choices and
//!   the feature loop; the features go straight into lane `k` of `hid4`;
//! - **MLPs**: a loop over the invocation's LANES samples whose body is one sample's MLP in
//!   named scalars, weights as literals: no loads but the inputs. (A first version kept the
//!   four samples together in `vec4`s, as the generic MLPs do to share each weight read: four
//!   times the code, which crashed Chromium's GPU process compiling the colour MLP.)
//! - **geometry features** (`geo_to_work`, `geo_from_work`, between the density and colour
//!   passes): one statement per feature. The generic loop over the uniform's count indexes
//!   `hid4` and `out4` at run time, and lavapipe then keeps those arrays in memory for every
//!   access of the pass: with the loops unrolled, the colour pass took half the time.
//!
//! The values are the generic kernels' (the frames on lavapipe are bit-identical): each MLP
//! output is summed over its inputs in order, as on the CPU.
//!
//! # The text, and its twin
//! The page generates the same text in `web/js/specialise.js` from the file it streamed; the
//! test `tests/web_specialise.rs` runs that script under node and fails when its output differs
//! from [`specialised_region`]'s by a byte. Numbers are written as hexadecimal words
//! (`bitcast<f32>(0x........u)`, `vec4<u32>(0x........u, ...)`): exact, and the same in both
//! languages without a float formatter (a decimal's shortest round-trip form differs between
//! them).
//!
//! Models whose MLPs hold more than [`MAX_SPECIALISED_WEIGHTS`] weights, or with a layer of more
//! than [`MAX_SPECIALISED_INPUTS`] inputs, keep the generic region (their code would grow past
//! what compilers take in reasonable time).

use crate::layout::GpuModel;

/// The line that opens the replaceable region of `render.wgsl`.
pub const BEGIN: &str = "// ---- specialise: begin\n";
/// The line that closes it.
pub const END: &str = "// ---- specialise: end\n";

/// At most this many MLP weights (proposal, density and colour together) are written into a
/// shader; larger models keep the generic MLPs.
pub const MAX_SPECIALISED_WEIGHTS: usize = 16384;

/// Layers with more inputs than this keep the generic MLPs (each output is one expression of
/// that many terms; every preset's layers have at most 64).
pub const MAX_SPECIALISED_INPUTS: usize = 64;

/// Why a model's kernels were not specialised.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SpecialiseError {
    #[error("the shader has no `specialise` region")]
    NoRegion,
    #[error(
        "the model's MLPs hold {0} weights; at most {MAX_SPECIALISED_WEIGHTS} are specialised"
    )]
    TooLarge(usize),
    #[error("an MLP layer has {0} inputs; at most {MAX_SPECIALISED_INPUTS} are specialised")]
    TooWide(usize),
    #[error("an MLP weight is not finite")]
    NotFinite,
    #[error("the parameter buffer's `rest` holds {have} values; the MLPs need {need}")]
    Short { have: usize, need: usize },
    /// The device refused the specialised shader (a bug, or a shader source whose other
    /// functions differ from what the generator writes for): the generic kernels stay.
    #[error("compiling them for the model failed: {0}")]
    Compile(String),
}

/// The weights the three MLPs of `model` hold.
pub fn mlp_weights(model: &GpuModel) -> usize {
    model.split.mlps.iter().map(|r| r.len()).sum()
}

/// `source` (a `render.wgsl`) with its `specialise` region replaced by [`specialised_region`]:
/// `model`'s encodings and MLPs, the weights read from `rest` (the parameter buffer's part after
/// the field's tables, as uploaded to the `rest` binding).
pub fn specialise_wgsl(
    source: &str,
    model: &GpuModel,
    rest: &[f32],
) -> Result<String, SpecialiseError> {
    let begin = source.find(BEGIN).ok_or(SpecialiseError::NoRegion)?;
    let end = source[begin..]
        .find(END)
        .map(|e| begin + e + END.len())
        .ok_or(SpecialiseError::NoRegion)?;
    let mlps = specialised_region(model, rest)?;
    let mut out = String::with_capacity(source.len() + mlps.len());
    out.push_str(&source[..begin]);
    out.push_str(&mlps);
    out.push_str(&source[end..]);
    Ok(out)
}

/// The region's replacement: the `specialise` lines around the seven generated functions (the
/// two encodings, the three MLPs, then the two geometry-feature transfers; see the module's
/// documentation).
pub fn specialised_region(model: &GpuModel, rest: &[f32]) -> Result<String, SpecialiseError> {
    let total = mlp_weights(model);
    if total > MAX_SPECIALISED_WEIGHTS {
        return Err(SpecialiseError::TooLarge(total));
    }
    let m = &model.model;
    let c = m.color;
    let widest = [
        m.proposal[1],
        m.proposal[2],
        m.density[1],
        m.density[2],
        16 + c[3],
        c[1],
    ]
    .into_iter()
    .max()
    .unwrap_or(0) as usize;
    if widest > MAX_SPECIALISED_INPUTS {
        return Err(SpecialiseError::TooWide(widest));
    }
    let need = model.split.mlps.iter().map(|r| r.end).max().unwrap_or(0);
    if rest.len() < need {
        return Err(SpecialiseError::Short {
            have: rest.len(),
            need,
        });
    }
    let mut w = Writer {
        out: String::new(),
        rest,
        finite: true,
    };
    w.out.push_str(BEGIN);
    w.out.push_str(
        "// Generated for one model (msth-gpu specialise.rs, web/js/specialise.js): the encodings\n\
         // with every level's values as constants, the MLPs with the weights as constants.\n",
    );
    w.encoding("encode_field4", ("field", &m.field), m, [0, 1], true);
    w.encoding("encode_proposal4", ("prop", &m.prop), m, [0, 1], false);
    // Proposal: in -> hidden (ReLU) -> 1.
    let (off, nin, hidden) = (
        m.proposal[0] as usize,
        m.proposal[1] as usize,
        m.proposal[2] as usize,
    );
    w.out
        .push_str("fn proposal_mlp4() -> vec4<f32> {\n    var r: vec4<f32>;\n");
    w.out.push_str(LOOP);
    w.inputs(nin);
    w.layer("x", "h", off, nin, hidden, true);
    w.sum_line(
        "        r[k] = ",
        "h",
        off + nin * hidden,
        hidden,
        1,
        0,
        ";\n",
    );
    w.out.push_str("    }\n    return r;\n}\n\n");
    // Density: in -> hidden (ReLU) -> 1 + geo, into out4.
    let (off, nin, hidden, nout) = (
        m.density[0] as usize,
        m.density[1] as usize,
        m.density[2] as usize,
        m.density[3] as usize,
    );
    w.out.push_str("fn density_mlp4() {\n");
    w.out.push_str(LOOP);
    w.inputs(nin);
    w.layer("x", "h", off, nin, hidden, true);
    for o in 0..nout {
        w.sum_line(
            &format!("        out4[{o}][k] = "),
            "h",
            off + nin * hidden,
            hidden,
            nout,
            o,
            ";\n",
        );
    }
    w.out.push_str("    }\n}\n\n");
    // Colour: 16 + geo -> hidden (ReLU) x layers -> 3, sigmoid.
    let (mut off, hidden, layers, nin) = (
        c[0] as usize,
        c[1] as usize,
        c[2] as usize,
        16 + c[3] as usize,
    );
    w.out
        .push_str("fn color_mlp4() -> array<vec4<f32>, 3> {\n    var r: array<vec4<f32>, 3>;\n");
    w.out.push_str(LOOP);
    w.inputs(nin);
    w.layer("x", "a0_", off, nin, hidden, true);
    off += nin * hidden;
    for k in 1..layers {
        let (from, to) = (format!("a{}_", k - 1), format!("a{k}_"));
        w.layer(&from, &to, off, hidden, hidden, true);
        off += hidden * hidden;
    }
    w.layer(&format!("a{}_", layers - 1), "c", off, hidden, 3, false);
    w.out.push_str(
        "        r[0][k] = sigmoid(c0);\n        r[1][k] = sigmoid(c1);\n        r[2][k] = sigmoid(c2);\n",
    );
    w.out.push_str("    }\n    return r;\n}\n\n");
    w.geo_transfers(c[3] as usize);
    w.out.push_str(END);
    if !w.finite {
        return Err(SpecialiseError::NotFinite);
    }
    Ok(w.out)
}

/// The loop over an invocation's samples that each function's body sits in.
const LOOP: &str = "    for (var k = 0u; k < LANES; k++) {\n";

/// `vec4<u32>(0x........u, ...)`.
fn words(w: [u32; 4]) -> String {
    format!(
        "vec4<u32>({:#010x}u, {:#010x}u, {:#010x}u, {:#010x}u)",
        w[0], w[1], w[2], w[3]
    )
}

struct Writer<'a> {
    out: String,
    rest: &'a [f32],
    finite: bool,
}

impl Writer<'_> {
    /// An encoding function (`encode_field4`, `encode_proposal4`): `encode` with every level's
    /// uniform values written as constants, the level loop unrolled, the features stored straight
    /// into lane `k` of `hid4`, the 4D lookups behind the caller's constant `with4` (false in
    /// `pass_proposal3` and `pass_density3`). `(uniform, e)`: the encoding's member of `Model` and its value;
    /// `buffers`: the 3D and 4D tables' buffers (0 `tab3`, 1 `tab4`); `returns`: whether
    /// it returns the mask value.
    fn encoding(
        &mut self,
        name: &str,
        (uniform, e): (&str, &crate::layout::EncodingU),
        m: &crate::layout::ModelU,
        buffers: [u32; 2],
        returns: bool,
    ) {
        let o = &mut self.out;
        o.push_str(&format!(
            "fn {name}(p: vec4<f32>, cutoff: f32, k: u32, with4: bool){} {{\n",
            if returns { " -> f32" } else { "" }
        ));
        o.push_str(&format!(
            "    let e = model.{uniform};\n    let m = mask_at(e, p.xyz);\n    let b = blend_of(e, m, cutoff);\n"
        ));
        o.push_str(
            "    let z = Feat(vec4<f32>(0.0), vec4<f32>(0.0));\n    var f3 = z;\n    var f4 = z;\n",
        );
        let grids = [
            (&e.h3, "f3", "b.z", buffers[0]),
            (&e.h4, "f4", "with4 && b.w", buffers[1]),
        ];
        let shape = if e.h3.loc[2] == 1 {
            e.h3.shape
        } else {
            e.h4.shape
        };
        let (nf, levels) = (shape[1], shape[2]);
        for l in 0..levels {
            o.push_str(&format!("    // level {l}\n"));
            for (g, f, on, buf) in grids {
                if g.loc[2] != 1 {
                    continue;
                }
                let lv = &m.levels[(g.loc[1] + l) as usize];
                o.push_str(&format!(
                    "    {f} = z;\n    if {on} != 0.0 {{ {f} = grid_level_at(Level(bitcast<vec4<f32>>({}), {}, {}), {}, p, {buf}u); }}\n",
                    words(lv.scale.map(f32::to_bits)),
                    words(lv.stride),
                    words(lv.info),
                    words(g.shape)
                ));
            }
            o.push_str(&format!("    let va{l} = b.x * f3.a + b.y * f4.a;\n"));
            if nf > 2 {
                o.push_str(&format!("    let vb{l} = b.x * f3.b + b.y * f4.b;\n"));
            }
            for f in 0..nf {
                let (v, c) = if f < 4 { ("va", f) } else { ("vb", f - 4) };
                o.push_str(&format!(
                    "    hid4[{}][k] = {v}{l}.{};\n",
                    l * nf + f,
                    ["x", "y", "z", "w"][c as usize]
                ));
            }
        }
        o.push_str(if returns {
            "    return m;\n}\n\n"
        } else {
            "}\n\n"
        });
    }

    /// `geo_to_work` and `geo_from_work` for `geo` geometry features: one statement per feature
    /// (the generic ones loop over a count from the uniform).
    fn geo_transfers(&mut self, geo: usize) {
        let o = &mut self.out;
        let at = format!("    let at = pass_u.reg1.x + j * {geo}u;\n");
        let plus = |q: usize| {
            if q == 0 {
                String::new()
            } else {
                format!(" + {q}u")
            }
        };
        o.push_str("fn geo_to_work(j: u32, k: u32) {\n");
        o.push_str(&at);
        for q in 0..geo {
            o.push_str(&format!("    work[at{}] = out4[{}][k];\n", plus(q), 1 + q));
        }
        o.push_str("}\n\nfn geo_from_work(j: u32, k: u32) {\n");
        o.push_str(&at);
        for q in 0..geo {
            o.push_str(&format!("    hid4[{}][k] = work[at{}];\n", 16 + q, plus(q)));
        }
        o.push_str("}\n");
    }

    /// `let x0 = hid4[0][k];` ... one line.
    fn inputs(&mut self, n: usize) {
        self.out.push_str("       ");
        for i in 0..n {
            self.out.push_str(&format!(" let x{i} = hid4[{i}][k];"));
        }
        self.out.push('\n');
    }

    /// The weight at `i` of `rest` as a WGSL expression.
    fn weight(&mut self, i: usize) -> String {
        let v = self.rest[i];
        self.finite &= v.is_finite();
        format!("bitcast<f32>({:#010x}u)", v.to_bits())
    }

    /// One output of a layer: `prefix` then `in_0 * W[0, o] + in_1 * W[1, o] + ...` (W
    /// `[nin, nout]` row-major at `off`) then `suffix`. Left to right, as the CPU sums.
    #[allow(clippy::too_many_arguments)]
    fn sum_line(
        &mut self,
        prefix: &str,
        input: &str,
        off: usize,
        nin: usize,
        nout: usize,
        o: usize,
        suffix: &str,
    ) {
        self.out.push_str(prefix);
        for i in 0..nin {
            if i > 0 {
                self.out.push_str(" + ");
            }
            let wt = self.weight(off + i * nout + o);
            self.out.push_str(&format!("{input}{i} * {wt}"));
        }
        self.out.push_str(suffix);
    }

    /// A layer: `let {to}o = max(sum, 0.0);` per output (ReLU), or `let {to}o = sum;`.
    fn layer(&mut self, from: &str, to: &str, off: usize, nin: usize, nout: usize, relu: bool) {
        for o in 0..nout {
            let (pre, post) = if relu {
                (format!("        let {to}{o} = max("), ", 0.0);\n")
            } else {
                (format!("        let {to}{o} = "), ";\n")
            };
            self.sum_line(&pre, from, off, nin, nout, o, post);
        }
    }
}
