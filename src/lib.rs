//! The `furnace` package composes the renderer, the coordinator and the worker. Its library
//! holds what only a composition of both needs: [`local::LocalLink`], the in-process link
//! between a worker and a coordinator (`furnace render`, `furnace serve --local-workers`).

pub mod local;
