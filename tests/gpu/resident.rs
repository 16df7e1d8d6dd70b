//! The map resident on the device.
