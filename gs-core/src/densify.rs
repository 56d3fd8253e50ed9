//! Adaptive density control: clone, split, prune, opacity reset.
