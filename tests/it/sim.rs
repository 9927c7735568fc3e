//! Simulator integration tests.
