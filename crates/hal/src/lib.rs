//! The hardware abstraction layer of viscoprobe: the instrument traits that every backend
//! (serial DAQ, simulated SPM) implements, and the safety layer that wraps them.
//!
//! Nothing is defined here yet: the traits, the safety layer and the simulated SPM arrive
//! with the HAL issue (#4), the serial DAQ driver with #5. The crate exists so that the
//! workspace has its final shape and the dependency direction (`hal → core`, never back)
//! is fixed from the start.
