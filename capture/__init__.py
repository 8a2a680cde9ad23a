"""Photos and exposure brackets to linear HDR radiance (RAW, LDR brackets, single JPEGs)."""
