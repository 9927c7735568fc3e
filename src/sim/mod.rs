//! The FE middle-ear simulator.
