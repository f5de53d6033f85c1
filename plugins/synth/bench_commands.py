"""The synthesis benches as ``btforge bench`` commands (each parses its own options)."""
from __future__ import annotations

import argparse
from btforge.bench import positive_count, print_figures


def _parser(name: str, fn) -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog=f"btforge bench {name}", description=fn.__doc__)


def bench_quilt(argv: list[str]) -> int:
    """Quilting 512 x 512 from a 128 x 128 9-D PTM exemplar: rejection vs brute force."""
    from .bench import benchmark_quilt
    p = _parser("quilt", bench_quilt)
    p.add_argument("--ptm", help="take the exemplar from the centre of this .ptm file (default: random smooth fields)")
    p.add_argument("--repeat", type=positive_count, default=5)
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = p.parse_args(argv)
    exemplar = None
    if args.ptm:
        from btforge import stage
        exemplar = stage("ptm.read")(path=args.ptm)["model"]
    print_figures(benchmark_quilt(repeat=args.repeat, exemplar=exemplar), args.json)
    return 0


def bench_kcoherence(argv: list[str]) -> int:
    """K-coherence 256 x 256, 3 levels, k = 6, 5 x 5 neighbourhood."""
    from .bench import benchmark_kcoherence
    p = _parser("kcoherence", bench_kcoherence)
    p.add_argument("--exemplar-size", type=int, default=64, help="exemplar side in texels (default 64)")
    p.add_argument("--repeat", type=positive_count, default=5)
    p.add_argument("--search", choices=("fast", "exact", "coherent"), default="fast", help="neighbourhood search engine")
    p.add_argument("--warm", action="store_true",
                   help="keep the cached analysis between repeats (time re-synthesis only; default: analyse cold)")
    p.add_argument("--texels", default="stack", metavar="stack|ptm|FILE.ptm",
                   help="exemplar texels: the demo material as a 16-light stack (32-D appearance vectors, default), "
                        "fitted as a 9-D orthonormal PTM (ptm), or the central square of a .ptm file")
    p.add_argument("--recall", type=int, default=0, metavar="N",
                   help="also measure the finest coherence sets against the exact search at N texels")
    p.add_argument("--blocks", type=int, default=0, metavar="N",
                   help="the stage's 'blocks': 0 (default) times the hierarchical synthesis over 3 levels, as "
                        "in Tong et al.; -1 (the stage's default) starts from stratified blocks")
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = p.parse_args(argv)
    print_figures(benchmark_kcoherence(args.exemplar_size, repeat=args.repeat, search=args.search,
                                       cold=not args.warm, texels=args.texels, recall_samples=args.recall,
                                       blocks=args.blocks),
                  args.json)
    return 0


COMMANDS = {"quilt": bench_quilt, "kcoherence": bench_kcoherence}
