//! What sits beside the engine, behind the `tools` cargo feature (on by default; the command line
//! needs it): the synthetic benchmark's renderer (`synth`), pictures of every stage, explain
//! sheets and precision-recall charts (`viz`), the large-map matching and store benchmarks with
//! their /proc readers (`bench`, `bench_store`), the stream replay benchmark (`bench_stream`) and the configuration sweeps (`tune`). The
//! engine never imports them (`tests/layering.rs`); an application embedding the engine turns the
//! feature off (`default-features = false`) and builds none of them.

pub mod bench;
pub mod bench_store;
pub mod bench_stream;
pub mod synth;
pub mod tune;
pub mod viz;
