"""Foreign logs (.asc, .blf, .trc written by python-can's own writers): replay says how many
frames decoded and which IDs no DBC file defines; a log with nothing decodable fails."""

import can
import pytest

from cell.app.cli import main

WRITERS = {".asc": can.ASCWriter, ".blf": can.BLFWriter, ".trc": can.TRCWriter}


def foreign_frames(t0=1.0):
    """Frames of an ECU the cell's DBC files do not describe, with a remote and an error frame."""
    out = []
    for i in range(5):
        out.append(can.Message(timestamp=t0 + 0.1 * i, arbitration_id=0x123, data=bytes(range(8)),
                               is_extended_id=False))
        out.append(can.Message(timestamp=t0 + 0.1 * i + 0.01, arbitration_id=0x18FEF100,
                               data=b"\x01\x02\x03\x04\x05\x06\x07\x08", is_extended_id=True))
    out.append(can.Message(timestamp=t0 + 0.6, arbitration_id=0x321, is_remote_frame=True, dlc=8,
                           is_extended_id=False))
    out.append(can.Message(timestamp=t0 + 0.7, is_error_frame=True))
    return out


def write(path, frames):
    with WRITERS[path.suffix](str(path)) as w:
        for m in frames:
            w.on_message_received(m)
    return path


@pytest.mark.parametrize("suffix", sorted(WRITERS))
def test_a_log_with_no_decodable_frame_fails_naming_the_ids(tmp_path, capsys, suffix):
    log = write(tmp_path / f"foreign{suffix}", foreign_frames())
    out = tmp_path / "out.csv"
    assert main(["replay", str(log), "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err
    assert "no frame decodes" in err and "0 decoded" in err, err
    assert "0x123 (5)" in err and "0x18FEF100x (5)" in err, err
    assert "--dbc" in err
    assert not out.exists()  # nothing half-written that looks like a result


@pytest.mark.parametrize("suffix", sorted(WRITERS))
def test_a_mixed_log_reports_decoded_and_unknown_and_lists_only_computed_channels(
        db, tmp_path, capsys, suffix):
    own = [db.encode("ENGINE_1", {"ENGINE_SPEED": 1500.0 + i, "ENGINE_TORQUE": 1000.0,
                                  "FUEL_RATE": 50.0, "ENGINE_POWER": 300.0}, 1.0 + 0.02 * i)
           for i in range(100)]
    frames = sorted(own + foreign_frames(), key=lambda m: m.timestamp)
    log = write(tmp_path / f"mixed{suffix}", frames)
    out, png = tmp_path / "out.csv", tmp_path / "out.png"
    assert main(["replay", str(log), "--out", str(out), "--plot", str(png), "--quiet"]) == 0
    err = capsys.readouterr().err
    written = list(can.LogReader(str(log)))  # python-can's TRC writer drops remote/error frames
    assert f"{len(written)} frames, 100 decoded" in err, err
    if any(m.is_remote_frame for m in written):
        assert "1 remote frame, 1 error frame" in err, err
    assert "0x123 (5)" in err, err
    header = out.read_text().splitlines()[0].split(",")
    assert "ENGINE_SPEED" in header and "EXH_BP_R_Kalman" not in header
    assert png.stat().st_size > 0
    # the Kalman filter exists in this runtime but computed nothing: not offered, not accepted
    assert main(["replay", str(log), "--out", str(out), "--channels", "EXH_BP_R_Kalman",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "no value for EXH_BP_R_Kalman" in err and "ENGINE_SPEED" in err
    assert "EXH_BP_L_MAF" not in err.split("computed:")[1]
