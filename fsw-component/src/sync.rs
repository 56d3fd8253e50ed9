//! Synchronizer: pairs camera frames with pose and Sun telemetry interpolated to the frame time.
