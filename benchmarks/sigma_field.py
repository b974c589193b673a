r"""Copy a contract bag with its stars' ``sigma`` field restated (issue 21 acceptance, fourth pass).

What a user whose tracker states its centroid noise wrongly brings: the same bag, every
message byte-identical except the ``sigma`` of the star centroids, multiplied by
``--scale`` (and, for stars at or fainter than ``--faint-mag``, by ``--faint-scale``
instead; 0 writes "unknown").  Used on the independent generator's bags::

    .venv/bin/python benchmarks/sigma_field.py ../shared/data/psce_ideal_900s.mcap OUT.mcap \
        --scale 1.0 --faint-mag 4.5 --faint-scale 0.5
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer

from stellar_cal_ros.io.cdr import decode_star_array, encode_star_frame
from stellar_cal_ros.io.schemas import STAR_ARRAY


def restate(src: Path, dst: Path, scale: float, faint_mag: float | None = None,
            faint_scale: float | None = None) -> int:
    """Write ``dst``: ``src`` with the stars' sigma restated; returns the star frames changed."""
    n = 0
    with open(src, "rb") as fi, open(dst, "wb") as fo:
        reader = make_reader(fi)
        w = Writer(fo)
        w.start(profile="ros2", library="stellar_cal_ros benchmarks/sigma_field.py")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id],
                    dict(channel.metadata))
            data = msg.data
            if schema.name == STAR_ARRAY:
                f = decode_star_array(data)
                k = np.full(len(f.sigma), scale)
                if faint_mag is not None:
                    k[np.asarray(f.magnitude) >= faint_mag] = faint_scale
                data = encode_star_frame(dataclasses.replace(f, sigma=np.asarray(f.sigma) * k))
                n += 1
            w.add_message(channels[channel.id], msg.log_time, data, msg.publish_time,
                          msg.sequence)
        w.finish()
    return n


def main() -> int:
    """Parse the arguments, copy the bag and its prior (``OUT.prior.yaml``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--faint-mag", type=float, default=None)
    ap.add_argument("--faint-scale", type=float, default=None)
    a = ap.parse_args()
    if (a.faint_mag is None) != (a.faint_scale is None):
        ap.error("--faint-mag and --faint-scale go together")
    n = restate(a.bag, a.out, a.scale, a.faint_mag, a.faint_scale)
    prior = a.bag.with_name(a.bag.name.removesuffix(".mcap") + ".prior.yaml")
    if prior.exists():
        a.out.with_name(a.out.name.removesuffix(".mcap") + ".prior.yaml").write_text(
            prior.read_text())
    print(f"{a.out}: {n} star frames, sigma x{a.scale:g}"
          + (f" (x{a.faint_scale:g} at mag >= {a.faint_mag:g})" if a.faint_mag is not None
             else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
