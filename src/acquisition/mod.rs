//! Scan sequences. (Being written.)
