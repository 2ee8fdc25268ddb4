// Runs the page's layer policy (web/js/abr.js `simulate`) on a `.msth` file over a simulated
// link and prints the session as JSON, for tests/tests/web_layers.rs to compare with
// msth-player's `abr::simulate`. Run from anywhere:
//   node web/tests/abr_sim.mjs FILE.msth LATENCY FRAMES FPS RATE[,RATE@SECONDS...]
// (rates in bytes/s; each `RATE@SECONDS` from that wall-clock second on).

import { readFileSync } from "node:fs";
import { Decoder, prefixLength } from "../js/format.js";
import { simulate } from "../js/abr.js";

const [file, latency, frames, fps, schedule] = process.argv.slice(2);
if (!schedule) {
  console.error("usage: node web/tests/abr_sim.mjs FILE.msth LATENCY FRAMES FPS RATE[,RATE@SECONDS...]");
  process.exit(2);
}
const bytes = new Uint8Array(readFileSync(file));
const dec = new Decoder(bytes.subarray(0, prefixLength(bytes.subarray(0, 32))));
const steps = schedule.split(",").map((s, i) => {
  const [rate, at] = s.split("@");
  return [i === 0 ? 0 : Number(at), Number(rate)];
});
const rateAt = (t) => {
  let r = steps[0][1];
  for (const [at, v] of steps) if (t >= at) r = v;
  return r;
};
const trace = simulate(dec, rateAt, Number(latency), Number(frames), Number(fps));
console.log(JSON.stringify(trace));
