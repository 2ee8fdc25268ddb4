//! Hash-table values that no training ray ever reached, found from the optimiser's state, so
//! that an export can drop them ("the export drops what nothing reaches", issue #8 item 3).
//!
//! A table value receives a gradient only when some training sample reads its row; Adam's second
//! moment `v` of a value that never got a nonzero gradient is exactly 0 (it only decays
//! afterwards: a value reached once with a gradient `g` keeps `v > 0` for about
//! `log(g^2 / 1e-45) / -log(beta2)` steps, tens of thousands for any gradient above ~1e-15).
//! Such values still hold their random initialisation (`U(-1e-4, 1e-4)`); [`zero_unreached`] sets
//! them to 0, which changes a render by at most that initial noise wherever a novel view reads
//! them, and which the codec stores almost for free (constant codes compress to nothing). The
//! mask grid and the MLPs are left alone (the mask loss reaches every mask vertex).

use msth_core::field::ModelLayout;
use serde::{Deserialize, Serialize};

use crate::adam::Adam;

/// Unreached values of one hash table (`field.h3`, `field.h4`, `proposal.h3`, `proposal.h4`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TableReach {
    pub name: String,
    pub values: usize,
    pub unreached: usize,
}

/// Whether a parameter entry is a hash table.
fn is_table(name: &str) -> bool {
    name.ends_with(".h3") || name.ends_with(".h4")
}

/// Counts, per hash table, the values whose Adam second moment is exactly 0.
pub fn unreached(layout: &ModelLayout, adam: &Adam) -> Vec<TableReach> {
    layout
        .params
        .entries
        .iter()
        .filter(|e| is_table(&e.name))
        .map(|e| TableReach {
            name: e.name.clone(),
            values: e.len,
            unreached: adam.v[e.range()].iter().filter(|&&v| v == 0.0).count(),
        })
        .collect()
}

/// Sets every hash-table value that no training ray reached (see the module docs) to 0 and
/// reports what it changed. Fails when the optimiser state does not match the parameters.
pub fn zero_unreached(
    layout: &ModelLayout,
    params: &mut [f32],
    adam: &Adam,
) -> Result<Vec<TableReach>, String> {
    if adam.v.len() != params.len() || params.len() != layout.params.total {
        return Err(format!(
            "the optimiser state has {} values for {} parameters (layout {})",
            adam.v.len(),
            params.len(),
            layout.params.total
        ));
    }
    for e in layout.params.entries.iter().filter(|e| is_table(&e.name)) {
        for (p, &v) in params[e.range()].iter_mut().zip(&adam.v[e.range()]) {
            if v == 0.0 {
                *p = 0.0;
            }
        }
    }
    Ok(unreached(layout, adam))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{generate, SynthConfig};
    use crate::train::{train, TrainSettings};
    use msth_core::config::Preset;

    /// A short real training: the coarse dense levels cover space no camera sees, so some table
    /// values stay unreached; zeroing them leaves the training views' renders unchanged.
    #[test]
    fn unreached_values_are_zeroed_and_renders_stay() {
        let cfg = SynthConfig {
            width: 24,
            height: 18,
            num_frames: 3,
            num_train_cams: 3,
            supersample: 1,
            ..Default::default()
        };
        let data = generate(&cfg);
        let mut s = TrainSettings::for_preset(Preset::Fast, &data);
        s.iters = 8;
        s.batch_rays = 256;
        s.checkpoint_every = 0;
        s.model.sampler.set_samples(16, 8);
        let dir = tempfile::tempdir().unwrap();
        let (trainer, _) = train(&data, s, dir.path(), None, &mut |_| true).unwrap();
        let layout = &trainer.layout;
        let mut params = trainer.params.clone();
        let report = zero_unreached(layout, &mut params, &trainer.adam).unwrap();
        let total: usize = report.iter().map(|r| r.unreached).sum();
        println!("{report:?}");
        assert!(report.iter().any(|r| r.name == "field.h3"));
        assert!(total > 0 && report.iter().all(|r| r.unreached < r.values));
        // Exactly the values with v == 0 changed, to 0; the rest are untouched.
        for (i, (&a, &b)) in trainer.params.iter().zip(&params).enumerate() {
            if a != b {
                assert_eq!(trainer.adam.v[i], 0.0);
                assert_eq!(b, 0.0);
            }
        }
        // A training view renders the same up to the initial noise the zeroed values held.
        let v = &data.train[0];
        let m = &trainer.settings.model;
        let a = crate::eval::render_image(m, layout, &trainer.params, &v.camera, v.time);
        let b = crate::eval::render_image(m, layout, &params, &v.camera, v.time);
        let d = a
            .rgb
            .iter()
            .zip(&b.rgb)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(d < 1e-3, "largest change {d}");
        // A mismatched optimiser state is an error, not a panic.
        let short = Adam::new(3);
        assert!(zero_unreached(layout, &mut params, &short).is_err());
    }
}
