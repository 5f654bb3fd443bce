//! The binary edge of viscoprobe: the `viscoprobe` command line (and, later, the
//! `viscoprobed` service). Everything here may touch files, the terminal and the clock;
//! the science it prints comes from `viscoprobe_core`.
pub mod cli;
pub mod config;
pub mod fan;
pub mod measure;
pub mod output;
pub mod plot;
pub mod service;
pub mod simrun;
