//! One whole scan. (Being written.)
