"""interop layer of bfpsf (see DESIGN.md data flow)."""
