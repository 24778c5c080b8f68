"""Hostile input files other than protocols: COMSOL field exports and tracker annotations.

Whatever the bytes, the readers raise their one documented error, naming the file, or
return data; nothing is ever executed from an input file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from magrun.field.comsol import ComsolFormatError, read_comsol_map
from magrun.tracking.dataset import load_annotations

FUZZ = settings(
    max_examples=600, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

HEADER = "% Model: x\n% Length unit: mm\n% x  y  mf.Bx (T)  mf.By (T)\n"
numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**40), 10**40).map(str),
    st.sampled_from(["", "x", "1e999", "-0", "0x10", "1,5", "nan", "%", "\t"]),
)
rows = st.lists(st.lists(numbers, min_size=0, max_size=6).map(" ".join), max_size=12)


comsol_files = st.one_of(
    st.builds(
        lambda header, body: (header + "\n".join(body) + "\n").encode(),
        st.sampled_from([HEADER, "", "% x y Bx By\n", "% x y z Bx By Bz\n"]),
        rows,
    ),
    st.binary(max_size=600),
)

COLUMNS = "image,tail_u,tail_v,centre_u,centre_v,head_u,head_v,comment"
cells = st.one_of(numbers, st.text(max_size=12), st.just('"quoted, cell"'))
annotation_files = st.one_of(
    st.builds(
        lambda header, body: (header + "\n" + "\n".join(body) + "\n").encode(),
        st.sampled_from([COLUMNS, "image,tail_u", "", "a,b,c"]),
        st.lists(st.lists(cells, min_size=0, max_size=9).map(",".join), max_size=10),
    ),
    st.binary(max_size=600),
)


@FUZZ
@given(data=comsol_files)
@example(data=b"% x y z Bx By Bz\n0.0 1.797693134862316e+296 0.0 0.0 0.0 0.0\n")  # overflowed
def test_comsol_exports_of_anything(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "map.txt"
    path.write_bytes(data)
    message = None
    try:
        read_comsol_map(path)
    except ComsolFormatError as exc:  # the one allowed failure
        message = str(exc)
    assert message is None or message.startswith(str(path))


@FUZZ
@given(data=annotation_files)
def test_annotation_files_of_anything(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "labels.csv"
    path.write_bytes(data)
    message = None
    try:
        labels = load_annotations(path)
    except ValueError as exc:  # the one allowed failure
        message = str(exc)
    if message is None:
        assert all(np.all(np.isfinite(points)) for _, points in labels)
    else:
        assert message.startswith(str(path))
