//! The tangent-map methods: symplectic splitting schemes as data ([`scheme`]), one orbit and its
//! deviation vectors stepped by a scheme's sub-maps ([`map`]), and many orbits at once in SIMD
//! lanes ([`batch`]).

pub mod batch;
pub mod map;
pub mod scheme;
