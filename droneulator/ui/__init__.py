"""The browser UI: level select, live camera views, a top-down map with click-to-fly (docs/ui.md)."""
