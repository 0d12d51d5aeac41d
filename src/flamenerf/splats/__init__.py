"""A trained run baked into coloured square splats with per-control linear offsets: the
format (`avatar`) and its reference rasteriser (`rasterise`)."""
