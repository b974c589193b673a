"""Placeholder for the `player` ROS 2 node (being written elsewhere)."""

import sys


def main(argv: list[str] | None = None) -> int:
    """Report that the node is not implemented yet; return 1."""
    print("player: not implemented yet", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
