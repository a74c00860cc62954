"""The vendored nuplan-devkit classes (python/tests/fixtures/nuplan_devkit) are the devkit's file unmodified: the
part below the licence header hashes to the upstream file's SHA-256 (motional/nuplan-devkit commit
e9241677997dd86bfc0bcd44817ab04fe631405b, nuplan/database/common/data_types.py)."""
import hashlib
from pathlib import Path

VENDOR = Path(__file__).resolve().parent / "fixtures" / "nuplan_devkit"
UPSTREAM_SHA256 = "8151180b93c99dda0ea1d9ec5d39644342783efc2a42fd1b3df47e5a9b8f381d"


def test_data_types_is_the_upstream_file():
    text = (VENDOR / "nuplan" / "database" / "common" / "data_types.py").read_bytes()
    header, sep, body = text.partition(b"# " + b"-" * 100 + b"\n")
    assert sep, "the header's closing line of dashes is missing"
    assert b"Licensed under the Apache License, Version 2.0" in header
    assert hashlib.sha256(body).hexdigest() == UPSTREAM_SHA256
    assert (VENDOR / "LICENSE.txt").read_text().startswith("Copyright 2021 Motional")
