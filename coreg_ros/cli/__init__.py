"""Command-line front ends: argparse only, each ``main(argv) -> int``."""
