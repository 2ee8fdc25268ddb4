// Kernels specialised to one model: the region of `render.wgsl` between its two `specialise`
// lines (the passes' encodings `encode_field4`, `encode_proposal4`, MLPs `proposal_mlp4`,
// `density_mlp4`, `color_mlp4` and geometry-feature transfers `geo_to_work`, `geo_from_work`)
// rewritten with the model's level values, MLP weights and feature count as constants, so that
// SwiftShader runs them without a per-lane gather for each level row, weight and activation read.
//
// The twin of msth-gpu's `gpu/src/specialise.rs`, which documents why: this file must write the
// same text byte for byte, and `tests/tests/web_specialise.rs` runs `web/tests/specialise.mjs`
// under node to check that it does. Numbers are written as hexadecimal words
// (`bitcast<f32>(0x........u)`, `vec4<u32>(0x........u, ...)`: exact, and the same in both
// languages).

import {
  MAX_SPECIALISED_INPUTS, MAX_SPECIALISED_WEIGHTS, MODEL_OFFSETS, ENCODING_OFFSETS, GRID_OFFSETS, LEVEL_OFFSETS, LEVEL_BYTES,
} from "./generated/contract.js";

export const BEGIN = "// ---- specialise: begin\n";
export const END = "// ---- specialise: end\n";

// The limits (generated from specialise.rs): at most MAX_SPECIALISED_WEIGHTS weights are written
// into a shader, and no layer may have more than MAX_SPECIALISED_INPUTS inputs.

/** The weights of the three MLPs (`m`: renderer.js `gpuModel`'s `mlps`). */
export const mlpWeights = (m) => m.ranges.reduce((n, [a, b]) => n + b - a, 0);

/**
 * The replacement of the `specialise` region for model `gm` (renderer.js `gpuModel`'s `mlps`,
 * the MLPs' uniform rows and weight ranges, and `uniform`, the `Model` uniform) whose `rest` values (a
 * Float32Array: the parameter buffer from the end of the field's tables) are given: the two
 * encodings with their levels unrolled, then the three MLPs, each a loop over the invocation's
 * LANES samples, one sample's MLP per trip in scalars, then the two geometry-feature transfers.
 * Throws an Error saying why a model is not specialised.
 */
export function specialisedRegion(gm, rest) {
  const m = gm.mlps;
  const total = mlpWeights(m);
  if (total > MAX_SPECIALISED_WEIGHTS) {
    throw new Error(`the model's MLPs hold ${total} weights; at most ${MAX_SPECIALISED_WEIGHTS} are specialised`);
  }
  const widest = Math.max(m.proposal[1], m.proposal[2], m.density[1], m.density[2], 16 + m.color[3], m.color[1]);
  if (widest > MAX_SPECIALISED_INPUTS) throw new Error(`an MLP layer has ${widest} inputs; at most ${MAX_SPECIALISED_INPUTS} are specialised`);
  const need = Math.max(...m.ranges.map(([, b]) => b));
  if (rest.length < need) throw new Error(`the parameter buffer's \`rest\` holds ${rest.length} values; the MLPs need ${need}`);
  const bits = new Uint32Array(rest.buffer, rest.byteOffset, rest.length);
  const parts = [];
  let finite = true;
  const weight = (i) => {
    finite &&= Number.isFinite(rest[i]);
    return `bitcast<f32>(0x${bits[i].toString(16).padStart(8, "0")}u)`;
  };
  const inputs = (n) => {
    let line = "       ";
    for (let i = 0; i < n; i++) line += ` let x${i} = hid4[${i}][k];`;
    parts.push(line + "\n");
  };
  // One output: `prefix` then in_0 * W[0, o] + in_1 * W[1, o] + ... (W [nin, nout] row-major at
  // `off`), then `suffix`; left to right, as the CPU sums.
  const sumLine = (prefix, input, off, nin, nout, o, suffix) => {
    const terms = [];
    for (let i = 0; i < nin; i++) terms.push(`${input}${i} * ${weight(off + i * nout + o)}`);
    parts.push(prefix + terms.join(" + ") + suffix);
  };
  const layer = (from, to, off, nin, nout, relu) => {
    for (let o = 0; o < nout; o++) {
      if (relu) sumLine(`        let ${to}${o} = max(`, from, off, nin, nout, o, ", 0.0);\n");
      else sumLine(`        let ${to}${o} = `, from, off, nin, nout, o, ";\n");
    }
  };
  const LOOP = "    for (var k = 0u; k < LANES; k++) {\n";
  // The `Model` uniform's words (gpuModel), for the encodings' levels.
  const u = new Uint32Array(gm.uniform);
  const at = (byte) => byte / 4;
  const words = (w) => `vec4<u32>(${Array.from(w, (x) => `0x${x.toString(16).padStart(8, "0")}u`).join(", ")})`;
  const row = (byte) => u.subarray(at(byte), at(byte) + 4);
  // `encode` with every level's uniform values written as constants, the level loop unrolled,
  // the features stored straight into lane k of hid4 (specialise.rs `encoding`).
  const encoding = (name, which, buffers, returns) => {
    const base = MODEL_OFFSETS[which];
    const grid = (g) => ({ shape: row(base + ENCODING_OFFSETS[g] + GRID_OFFSETS.shape), loc: row(base + ENCODING_OFFSETS[g] + GRID_OFFSETS.loc) });
    const h3 = grid("h3");
    const h4 = grid("h4");
    parts.push(`fn ${name}(p: vec4<f32>, cutoff: f32, k: u32, with4: bool)${returns ? " -> f32" : ""} {\n`);
    parts.push(`    let e = model.${which};\n    let m = mask_at(e, p.xyz);\n    let b = blend_of(e, m, cutoff);\n`);
    parts.push("    let z = Feat(vec4<f32>(0.0), vec4<f32>(0.0));\n    var f3 = z;\n    var f4 = z;\n");
    const shape = h3.loc[2] === 1 ? h3.shape : h4.shape;
    const [nf, levels] = [shape[1], shape[2]];
    for (let l = 0; l < levels; l++) {
      parts.push(`    // level ${l}\n`);
      for (const [g, f, on, buf] of [[h3, "f3", "b.z", buffers[0]], [h4, "f4", "with4 && b.w", buffers[1]]]) {
        if (g.loc[2] !== 1) continue;
        const lv = MODEL_OFFSETS.levels + LEVEL_BYTES * (g.loc[1] + l);
        parts.push(
          `    ${f} = z;\n    if ${on} != 0.0 { ${f} = grid_level_at(Level(bitcast<vec4<f32>>(${words(row(lv + LEVEL_OFFSETS.scale))}), ` +
            `${words(row(lv + LEVEL_OFFSETS.stride))}, ${words(row(lv + LEVEL_OFFSETS.info))}), ${words(g.shape)}, p, ${buf}u); }\n`,
        );
      }
      parts.push(`    let va${l} = b.x * f3.a + b.y * f4.a;\n`);
      if (nf > 2) parts.push(`    let vb${l} = b.x * f3.b + b.y * f4.b;\n`);
      for (let f = 0; f < nf; f++) {
        const [v, c] = f < 4 ? ["va", f] : ["vb", f - 4];
        parts.push(`    hid4[${l * nf + f}][k] = ${v}${l}.${"xyzw"[c]};\n`);
      }
    }
    parts.push(returns ? "    return m;\n}\n\n" : "}\n\n");
  };
  parts.push(BEGIN);
  parts.push(
    "// Generated for one model (msth-gpu specialise.rs, web/js/specialise.js): the encodings\n" +
      "// with every level's values as constants, the MLPs with the weights as constants.\n",
  );
  encoding("encode_field4", "field", [0, 1], true);
  encoding("encode_proposal4", "prop", [0, 1], false);
  {
    const [off, nin, hidden] = m.proposal;
    parts.push("fn proposal_mlp4() -> vec4<f32> {\n    var r: vec4<f32>;\n", LOOP);
    inputs(nin);
    layer("x", "h", off, nin, hidden, true);
    sumLine("        r[k] = ", "h", off + nin * hidden, hidden, 1, 0, ";\n");
    parts.push("    }\n    return r;\n}\n\n");
  }
  {
    const [off, nin, hidden, nout] = m.density;
    parts.push("fn density_mlp4() {\n", LOOP);
    inputs(nin);
    layer("x", "h", off, nin, hidden, true);
    for (let o = 0; o < nout; o++) sumLine(`        out4[${o}][k] = `, "h", off + nin * hidden, hidden, nout, o, ";\n");
    parts.push("    }\n}\n\n");
  }
  {
    let [off, hidden, layers, geo] = m.color;
    const nin = 16 + geo;
    parts.push("fn color_mlp4() -> array<vec4<f32>, 3> {\n    var r: array<vec4<f32>, 3>;\n", LOOP);
    inputs(nin);
    layer("x", "a0_", off, nin, hidden, true);
    off += nin * hidden;
    for (let k = 1; k < layers; k++) {
      layer(`a${k - 1}_`, `a${k}_`, off, hidden, hidden, true);
      off += hidden * hidden;
    }
    layer(`a${layers - 1}_`, "c", off, hidden, 3, false);
    parts.push("        r[0][k] = sigmoid(c0);\n        r[1][k] = sigmoid(c1);\n        r[2][k] = sigmoid(c2);\n");
    parts.push("    }\n    return r;\n}\n\n");
  }
  {
    // The geometry-feature transfers, one statement per feature (specialise.rs `geo_transfers`).
    const geo = m.color[3];
    const at = `    let at = pass_u.reg1.x + j * ${geo}u;\n`;
    const plus = (q) => (q === 0 ? "" : ` + ${q}u`);
    parts.push("fn geo_to_work(j: u32, k: u32) {\n", at);
    for (let q = 0; q < geo; q++) parts.push(`    work[at${plus(q)}] = out4[${1 + q}][k];\n`);
    parts.push("}\n\nfn geo_from_work(j: u32, k: u32) {\n", at);
    for (let q = 0; q < geo; q++) parts.push(`    hid4[${16 + q}][k] = work[at${plus(q)}];\n`);
    parts.push("}\n");
  }
  parts.push(END);
  if (!finite) throw new Error("an MLP weight is not finite");
  return parts.join("");
}

/** `source` (a `render.wgsl`) with its `specialise` region replaced (`specialisedRegion`). */
export function specialiseWgsl(source, gm, rest) {
  const begin = source.indexOf(BEGIN);
  const endAt = begin < 0 ? -1 : source.indexOf(END, begin);
  if (endAt < 0) throw new Error("the shader has no `specialise` region");
  return source.slice(0, begin) + specialisedRegion(gm, rest) + source.slice(endAt + END.length);
}
