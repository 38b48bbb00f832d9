"""The studies over many solves (docs/DESIGN.md section 6): error maps (also over several
processes), local and global sensitivity, the multi-model summary.

Imports the entry point ``_solve`` and the layers below it, never the fit, the paper layer,
the plots or the CLI."""
