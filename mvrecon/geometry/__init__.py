"""Pure numpy geometry: arrays in, arrays out, no file access, no mvrecon imports outside this package."""
