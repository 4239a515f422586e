"""The Lamina terminal UI (Textual): ``lamina tui``."""
