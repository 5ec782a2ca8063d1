"""HTTP service and command line of omnisplat."""
