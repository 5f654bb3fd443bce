//! The science core of viscoprobe: pure computation, no I/O.
//!
//! An indentation measurement becomes parameter estimation. [`prony::PronySeries`] is the
//! material (creep compliance, moduli); [`contact::Contact`] turns force and indentation into
//! the linear pair (u, y) whose map is that compliance; [`discrete::Sampling`] says how the
//! model meets sampled data. The estimators in [`estimate`] (the paper's ARX, frequency-domain
//! maximum likelihood, time-domain output error) return an [`estimate::Estimate`] with
//! covariance and 95 % intervals; [`fisher`] gives the Cramér–Rao bound they are judged by.
//! [`design`] chooses the multisine that maximises that information (certified D-optimal) and
//! runs the design → measure → estimate loop as a state machine; [`miic`] makes an instrument
//! follow the design. [`twin`] is the physics of the simulated instrument; [`recording`] and
//! [`jpk`] read and write measurements; [`analysis`] fits a recording; [`studies`] regenerates
//! the paper's simulation studies.
//!
//! Nothing here touches files, sockets, threads or clocks: readers and writers come from the
//! caller, and every random process takes a seed.
pub mod analysis;
pub mod contact;
pub mod design;
pub mod diagnose;
pub mod discrete;
pub mod estimate;
pub mod fan;
pub mod fisher;
pub mod jpk;
pub mod linalg;
pub mod miic;
pub mod prony;
pub mod recording;
pub mod studies;
pub mod twin;
