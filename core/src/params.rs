//! One flat `f32` parameter buffer with named slices (tiny-cuda-nn's `set_params` idea): the
//! optimiser, the checkpoint and the codec all see the same layout.

use std::ops::Range;

use serde::{Deserialize, Serialize};

/// A named slice of the flat buffer.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ParamEntry {
    pub name: String,
    pub offset: usize,
    pub len: usize,
}

impl ParamEntry {
    pub fn range(&self) -> Range<usize> {
        self.offset..self.offset + self.len
    }
}

/// The layout of the whole buffer, in order.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ParamLayout {
    pub entries: Vec<ParamEntry>,
    pub total: usize,
}

impl ParamLayout {
    /// Appends a slice of `len` floats, 16-float aligned, and returns its range.
    pub fn push(&mut self, name: &str, len: usize) -> Range<usize> {
        let offset = self.total.div_ceil(16) * 16;
        self.entries.push(ParamEntry {
            name: name.to_string(),
            offset,
            len,
        });
        self.total = offset + len;
        offset..offset + len
    }

    pub fn get(&self, name: &str) -> Option<&ParamEntry> {
        self.entries.iter().find(|e| e.name == name)
    }
}
