//! One integration-test binary (one link step on 2 cores).
mod alternatives;
mod baseline;
mod cli;
mod diagnose_null;
mod discrepancy;
mod fuzz;
mod http;
mod npe;
mod pg;
mod physics;
mod resume;
mod retry;
mod s3;
mod sim;
mod slow_clients;
mod tenants;
mod train_resume;
