"""Command line: ``python -m addon demo`` (no Blender needed) and
``python -m addon bake SCENE.blend --out DIR`` (needs the bpy module; see addon/bake/cli.py).
"""

import argparse
import sys


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m addon", description="Caustic Bake command line")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="solve and print the caustic paths of two small sample scenes")
    demo.add_argument("--width", type=int, default=64, help="receiver grid columns (default 64)")
    demo.add_argument("--height", type=int, default=28, help="receiver grid rows (default 28)")
    bake = sub.add_parser("bake", help="bake the caustics of a .blend into EXR irradiance textures (needs the bpy module)")
    from .bake.cli import add_arguments

    add_arguments(bake)
    args = parser.parse_args(argv)
    if args.command == "bake":
        from .bake.cli import run

        return run(args)
    if args.command == "demo":
        if args.width < 1 or args.height < 1:
            parser.error("--width and --height must be positive")
        from .demo import run_demo

        run_demo(args.width, args.height)
    return 0


if __name__ == "__main__":
    sys.exit(main())
