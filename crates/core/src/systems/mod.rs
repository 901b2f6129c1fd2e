//! Systems H = ½|p|² + V(q): the [`Hamiltonian`](hamiltonian::Hamiltonian) trait and
//! Hénon–Heiles ([`hamiltonian`]), the Taylor recursions of a system ([`series`]) and polynomial
//! potentials read from text ([`polynomial`]).

pub mod hamiltonian;
pub mod polynomial;
pub mod series;
