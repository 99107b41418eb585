"""prism3d.atr: camouflage removal, profile/range/size features, training-chip
rendering, correlation filter banks and recognition evaluation."""
