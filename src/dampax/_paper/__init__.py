"""The papers' layer (docs/DESIGN.md section 6): their cases and quoted numbers, and
``reproduce`` (the numbers, figures and tables of both papers)."""
