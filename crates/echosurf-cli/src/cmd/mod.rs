//! One module per subcommand.
pub mod batch;
pub mod bench;
pub mod compare;
pub mod demo;
pub mod eval;
pub mod extract;
pub mod fit;
pub mod inspect;
pub mod outputs;
pub mod reconstruct;
pub mod render;
pub mod sample;
pub mod segment;
pub mod simulate;
pub mod slicer;
pub mod space;
pub mod surface;
