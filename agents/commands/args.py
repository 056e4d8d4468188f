"""The argument helpers the commands share: ``--set``, the backend options. What they parse is checked where the
library can check it too (:mod:`bimp.agents.errors`: overrides, labels, output folders)."""

from __future__ import annotations

import argparse

from bimp.agents.errors import EvaluationError, check_out_dir, parse_labels, parse_overrides  # noqa: F401  (one import for a command)


def add_set_argument(parser: argparse.ArgumentParser,
                     help: str | None = "config override for one policy, e.g. enkts.n_particles=100") -> None:
    """``--set POLICY.KEY=VALUE ...`` (parsed by :func:`parse_overrides`)."""
    # extend: a repeated flag adds to the earlier ones instead of silently replacing them
    parser.add_argument("--set", dest="overrides", nargs="*", action="extend", default=[],
                        metavar="POLICY.KEY=VALUE", help=help)


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    """``--backend``, ``--address``, ``--ray-cpus`` (read back by :func:`backend_options`)."""
    parser.add_argument("--backend", default="local", help="where the episodes run: local (a process pool of "
                        "--workers) or ray (a Ray cluster: docs/scaling.md)")
    parser.add_argument("--address", default=None, help="with --backend ray: the cluster's head HOST:PORT, "
                        "ray://HOST:PORT or auto (default: a new local Ray instance)")
    parser.add_argument("--ray-cpus", type=int, default=None, metavar="N",
                        help="with --backend ray and no --address: CPUs of the new local instance (default: all)")


def backend_options(args: argparse.Namespace) -> dict:
    """The keyword arguments of ``evaluate`` (and of what calls it) that :func:`add_backend_arguments` parsed."""
    return {"backend": args.backend, "address": args.address, "ray_cpus": args.ray_cpus}
