//! Sparse linear algebra shared by the solvers: fill-reducing orderings ([`ordering`]) and the
//! supernodal triangular sweeps ([`supernodal`]).

pub mod ordering;
pub mod supernodal;
