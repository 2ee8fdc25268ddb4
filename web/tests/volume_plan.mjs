// Plans the play-time volume of a `.msth` file as the page does (web/js/volume.js) and prints
// the plan as JSON: resolution, brick side, the static, dynamic and left-out bricks, the dynamic
// cells' bits, the slice times and the thresholds. `tests/tests/web_volume.rs` compares it with
// msth-player's plan of the same file. Run from anywhere:
//   node web/tests/volume_plan.mjs FILE.msth BUDGET_BYTES [auto|exact|bake]

import { readFileSync } from "node:fs";
import { Decoder, prefixLength } from "../js/format.js";
import { cameraFromJson } from "../js/camera.js";
import { planVolume } from "../js/volume.js";

const [file, budget, outside = "auto"] = process.argv.slice(2);
if (!file || !budget) {
  console.error("usage: node web/tests/volume_plan.mjs FILE.msth BUDGET_BYTES");
  process.exit(2);
}
const bytes = new Uint8Array(readFileSync(file));
const dec = new Decoder(bytes.subarray(0, prefixLength(bytes.subarray(0, 32))));
dec.sections.forEach((s, i) => dec.decodeSection(i, bytes.subarray(s.offset, s.offset + s.length)));
const meta = dec.metadata;
try {
  const plan = planVolume({
    model: meta.model,
    layout: dec.layout,
    params: dec.paramsForTime(0),
    occupancy: dec.occupancy,
    cameras: meta.cameras.map(cameraFromJson),
    budget: Number(budget),
    outside,
  });
  console.log(
    JSON.stringify({
      resolution: plan.geometry.resolution,
      brick: plan.geometry.brick,
      static_bricks: plan.staticBricks,
      dynamic_bricks: plan.dynamicBricks,
      dynamic_cells: Array.from(plan.dynamicCells),
      outside_bricks: plan.outsideBricks,
      slice_times: plan.sliceTimes,
      resident_slices: plan.residentSlices,
      density_threshold: plan.densityThreshold,
      proposal_threshold: plan.proposalThreshold,
    }),
  );
} catch (e) {
  console.log(JSON.stringify({ error: e.message }));
}
