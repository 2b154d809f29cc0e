"""Write Sylva's procedurally drawn leaf textures to resources/leaves/<shape>.png.

Run from the repository root in the venv::

    python scripts/make_leaf_textures.py [--size 256] [--out resources/leaves]

The images are drawn by :func:`sylva.core.textures.leaf_texture` (numpy only,
no copied images) and written through Pillow when installed, else through the
built-in zlib PNG writer.  tests/test_leaves.py checks that the shipped files
still match the drawing.
"""
import argparse
from pathlib import Path

from sylva.core.textures import LEAF_SHAPES, leaf_texture, write_png


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="texture size in pixels (square)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "resources" / "leaves",
                        help="output folder")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for shape in LEAF_SHAPES:
        path = write_png(args.out / f"{shape}.png", leaf_texture(shape, args.size))
        print(f"{path}  {path.stat().st_size / 1024:.1f} KiB")


if __name__ == "__main__":
    main()
