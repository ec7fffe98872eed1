"""model layer of bfpsf (see DESIGN.md data flow)."""
