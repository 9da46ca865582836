"""lvenv.archive: a study's finished records resume only under the settings that made them."""

import pytest

from lvenv.archive import ArchiveError, load_records, save_records


def test_records_round_trip_and_refuse_other_settings(tmp_path):
    path = tmp_path / "study.npz"
    settings = {"truths": 20, "seed": 1, "chain_steps": 1200}
    assert load_records(path, settings) == [], "no file: nothing done yet"
    records = [{"truth": 0, "inside": {"tau2": True}, "interval": [0.1, 0.25]}, {"truth": 1, "inside": {"tau2": False}, "interval": [0.2, 0.3]}]
    save_records(path, records, settings)
    assert load_records(path, dict(settings)) == records
    with pytest.raises(ArchiveError, match="seed"):
        load_records(path, {**settings, "seed": 2})
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(ArchiveError, match="damaged"):
        load_records(path, settings)
