"""The knnrefine command line: one module per subcommand, ``main(argv=None)`` in main.py."""
