//! Furnace's coordinator: jobs, chunk leases, the exact merge of partial accumulations, and
//! their persistence, behind the HTTP API of `furnace serve`.
//!
//! - [`job`]: one job's core (plan, chunk states and epochs, merge, noise-target control),
//!   with no I/O;
//! - [`state`]: the [`Coordinator`] (the jobs, the scheduler, the worker registry) and the
//!   functions that keep slow work out of its lock;
//! - [`store`]: the [`Store`] trait and its two stores, on disk and in memory;
//! - [`api`]: the HTTP API, the only place where errors become statuses.

pub mod api;
mod error;
pub mod job;
pub mod state;
pub mod store;

pub use api::{router, run, AppState};
pub use error::CoordError;
pub use state::Coordinator;
pub use store::{DiskStore, MemStore, Store};
