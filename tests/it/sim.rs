//! Simulator integration tests (verification against closed forms live in src/sim unit tests).
