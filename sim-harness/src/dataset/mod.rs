//! Dataset writer: frames, masks, depth, telemetry, evaluation views, points, plots.
