//! The science core of viscoprobe: pure computation, no I/O.
pub mod analysis;
pub mod contact;
pub mod design;
pub mod discrete;
pub mod estimate;
pub mod fisher;
pub mod jpk;
pub mod linalg;
pub mod miic;
pub mod prony;
pub mod recording;
pub mod studies;
pub mod twin;
