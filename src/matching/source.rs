//! The reference sources matching reads (defined in [`crate::descriptors::source`]).

pub use crate::descriptors::source::*;
