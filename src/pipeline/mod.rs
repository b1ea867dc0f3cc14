//! Reconstruction: pure functions over frames and cameras. (Being written.)
