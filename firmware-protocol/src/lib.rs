//! The scanrig serial line protocol (see `PROTOCOL.md`): a `no_std`, sans-IO codec.
#![cfg_attr(not(feature = "std"), no_std)]
