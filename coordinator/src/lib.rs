//! Furnace's coordinator: jobs, chunk leases, the exact merge of partial accumulations, and
//! their persistence, behind the HTTP API of `furnace serve`.

pub mod api;
pub mod state;

pub use api::{router, run, AppState};
pub use state::{CoordError, Coordinator};
