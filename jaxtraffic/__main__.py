"""``python -m jaxtraffic train|evaluate [flags]``: the two command lines (``train.py``, ``evaluate.py``)."""

from __future__ import annotations

import sys

USAGE = ("usage: python -m jaxtraffic {train,evaluate} [flags]   (python -m jaxtraffic train [ppo|gradient] --help "
         "lists them)")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):  # asked for (or nothing to do): usage on stdout, not an error
        print(USAGE)
        return 0
    if argv[0] not in ("train", "evaluate"):
        print(USAGE, file=sys.stderr)
        print(f"python -m jaxtraffic: error: unknown command {argv[0]!r}", file=sys.stderr)
        return 2
    if argv[0] == "train":
        from jaxtraffic.cli.train import main as train

        train(argv[1:])
    else:
        from jaxtraffic.cli.evaluate import main as evaluate

        evaluate(argv[1:])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
