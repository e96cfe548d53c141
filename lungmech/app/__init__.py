"""The application: scene files, runs with their outputs and pictures, the reduced-model and
registration workflows, and the command line. Nothing in the library imports this package."""
