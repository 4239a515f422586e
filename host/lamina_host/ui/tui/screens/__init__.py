"""The six workflow screens of the Lamina terminal UI."""
