"""The front ends beside the command line: the terminal UI and the browser UI that
serves it."""
