//! Arithmetic: the number types every integrator is generic over — f64, SIMD lanes of it
//! ([`real`]) and double-double ([`dd`]).

pub mod dd;
pub mod real;
