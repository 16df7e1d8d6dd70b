//! The device runtime every GPU executor runs on, as [`crate::nn`] is the CPU networks': the wgpu
//! context and its options, errors and counters ([`context`]), every kernel's pipeline and bind
//! group layout ([`kernels`], from the kernels crate's table), buffer helpers ([`buffers`]), what the networks' executors share ([`executor`]), the
//! pass timer ([`timer`]) and the adapter statistics ([`stats`]). It imports no stage and no
//! network: the stages' executors (`gpu`) and the networks' (`networks::*::device`) both sit on it.
//! Its public types are shown as `gpu`'s ([`crate::gpu::GpuContext`] and the others).

pub(crate) mod buffers;
pub(crate) mod context;
pub(crate) mod executor;
pub(crate) mod kernels;
pub(crate) mod stats;
pub(crate) mod timer;
