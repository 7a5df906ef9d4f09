//! The checks behind the fuzz targets (`fuzz_targets/`): one function per
//! target that decodes one input and panics exactly when an invariant
//! breaks. The workspace crates' `tests/integration/fuzz_corpus.rs` include the same
//! files with `#[path]` and replay `corpus/<target>/` through them.

/// One module per crate whose decoders are checked.
pub mod checks {
    pub mod corpus;
    pub mod observation;
    pub mod robot_agent;
    pub mod runtime;
    pub mod tracker;
}
