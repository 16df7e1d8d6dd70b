//! The fine stage on the device.
