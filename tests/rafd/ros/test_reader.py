"""Reading radar scans out of bags: each message type and layout, and each bad input (a clear BagError naming the
topic and message)."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.ros import types
from rafd.ros.answers import header
from rafd.ros.build import make
from rafd.ros.reader import BagError, read_scans, scan_topic
from rafd.ros.scans import RadarGeometry
from rafd.ros.sequence import native_scan_of
from rafd.ros.writer import BagWriter
from rafd.scans.native import HEADER_COLUMNS
from tests.rafd.ros.conftest import native_scans
from tools.navtech_bag import b_scan_message, write_navtech_bag


def read_all(bag: Path, topic: str | None = None, flags: RadarGeometry | None = None):
    return [scan for _, scan in read_scans(scan_topic(bag, topic, flags))]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("layout", ["typed", "legacy"])
def test_a_navtech_b_scan_bag_gives_back_its_native_scans(tmp_path: Path, scans, storage: str, layout: str):
    """RadarBScanMsg + either layout of RadarConfigurationMsg, either storage: the native scans come back exactly
    (times, encoder angles, bins), at the driver's stamp (azimuth 199), with the configuration's bin size."""
    bag = write_navtech_bag(tmp_path / "bag", scans, 0.0864, storage, layout)
    for direct in (bag, next(bag.glob("*.mcap"), None) or next(bag.glob("*.db3"))):  # the folder or its file
        read = read_all(direct)
        assert len(read) == len(scans)
        for original, scan in zip(scans, read):
            assert scan.layout == "native" and scan.range_bin_m == pytest.approx(0.0864)
            np.testing.assert_array_equal(scan.pixels, original)
            stamp_us = int(np.ascontiguousarray(original[199, :8]).view("<i8")[0])
            assert scan.stamp_ns == stamp_us * 1000
            assert native_scan_of(scan).fmt.range_bin_m == pytest.approx(0.0864)


def test_without_a_configuration_the_flags_give_the_geometry(tmp_path: Path, scans):
    from tools.navtech_bag import write_navtech_bag as write

    bag = write(tmp_path / "bare", scans, 0.0432, with_configuration=False)
    assert read_all(bag)[0].range_bin_m is None  # the service will read the width
    assert read_all(bag, flags=RadarGeometry(range_bin_m=0.05))[0].range_bin_m == 0.05


def _image_bag(path: Path, messages: list[tuple[str, str, object, int]], storage: str = "mcap") -> Path:
    with BagWriter(path, storage) as bag:
        for topic, msgtype, message, stamp in messages:
            bag.write(topic, msgtype, stamp, message)
    return path


def _image(store, pixels: np.ndarray, stamp: int):
    return make(
        store,
        types.IMAGE,
        header=header(store, stamp, "radar"),
        height=pixels.shape[0],
        width=pixels.shape[1],
        encoding="mono8",
        step=pixels.shape[1],
        data=np.ascontiguousarray(pixels).reshape(-1),
    )


def test_images_native_plain_polar_and_png(tmp_path: Path, scans):
    """sensor_msgs/Image with header columns (as the datasets store scans) comes back as it is; a plain B-scan (no
    header columns) gets evenly spread times and angles centred on its stamp; a RADIATE polar image stays polar; a
    CompressedImage PNG reads like the Image."""
    store = types.typestore()
    native = scans[0]
    plain = native[:, HEADER_COLUMNS:]
    polar = np.zeros((576, 400), np.uint8)
    stamp = 1_547_131_046_125_000_000
    png = cv2.imencode(".png", native)[1].tobytes()
    compressed = make(
        store,
        types.COMPRESSED_IMAGE,
        header=header(store, stamp, "radar"),
        format="png",
        data=np.frombuffer(png, np.uint8),
    )
    cases = {
        "native": (types.IMAGE, _image(store, native, stamp)),
        "plain": (types.IMAGE, _image(store, plain, stamp)),
        "polar": (types.IMAGE, _image(store, polar, stamp)),
        "png": (types.COMPRESSED_IMAGE, compressed),
    }
    for name, (msgtype, message) in cases.items():
        bag = _image_bag(tmp_path / name, [("/radar/scan", msgtype, message, stamp)])
        (scan,) = read_all(bag, flags=RadarGeometry(range_bin_m=0.0432))
        assert scan.stamp_ns == stamp and scan.frame_id == "radar"
        if name == "polar":
            assert scan.layout == "polar" and scan.pixels.shape == (576, 400)
            continue
        assert scan.layout == "native"
        np.testing.assert_array_equal(scan.pixels[:, HEADER_COLUMNS:], plain)
        read = native_scan_of(scan)
        if name == "plain":
            middle = (read.timestamps_us[199] + read.timestamps_us[200]) / 2
            assert (
                abs(middle - stamp / 1000) < 1 and 0.24 < (read.timestamps_us[-1] - read.timestamps_us[0]) / 1e6 < 0.26
            )
            assert read.encoder[0] == 0 and read.encoder[100] == 1400
        else:
            np.testing.assert_array_equal(scan.pixels, native)


def test_a_scan_topic_is_found_by_type_or_named(tmp_path: Path, scans):
    store = types.typestore()
    stamp = 1_547_131_046_125_000_000
    message, _ = b_scan_message(store, scans[0])
    bag = _image_bag(
        tmp_path / "two",
        [
            ("/radar/b_scan", types.B_SCAN, message, stamp),
            ("/camera", types.IMAGE, _image(store, np.zeros((4, 4), np.uint8), stamp), stamp),
            ("/radar/b_scan_copy", types.B_SCAN, message, stamp),
        ],
    )
    with pytest.raises(BagError, match=r"2 topics of type navtech_msgs/msg/RadarBScanMsg .*--topic"):
        scan_topic(bag)
    assert scan_topic(bag, "/radar/b_scan_copy").topic == "/radar/b_scan_copy"
    with pytest.raises(BagError, match="no topic /radar/missing; the bag holds"):
        scan_topic(bag, "/radar/missing")
    with pytest.raises(BagError, match=r"topic /camera, message 0: image of 4 x 4"):
        read_all(bag, "/camera")


# ---------------------------------------------------------------------------------------------- bad input
def test_a_topic_of_another_type_is_refused_naming_it(tmp_path: Path):
    store = types.typestore()
    status = make(store, "std_msgs/msg/String", data="hello")
    bag = _image_bag(tmp_path / "strings", [("/status", "std_msgs/msg/String", status, 1)])
    with pytest.raises(BagError, match=r"topic /status is of type std_msgs/msg/String; rafd reads radar scans"):
        scan_topic(bag, "/status")
    with pytest.raises(BagError, match=r"no radar scan topic .* the bag holds /status \(std_msgs/msg/String\)"):
        scan_topic(bag)


def test_a_message_that_does_not_decode_as_its_type_is_refused(tmp_path: Path, scans):
    """A connection that says RadarBScanMsg but carries something else (a mismatched type)."""
    store = types.typestore()
    bag_path = tmp_path / "mismatched"
    with BagWriter(bag_path) as bag:
        connection = bag.writer.add_connection("/radar/b_scan", types.B_SCAN, typestore=store)
        bag.connections["/radar/b_scan"] = connection
        text = store.serialize_cdr(make(store, "std_msgs/msg/String", data="not a scan"), "std_msgs/msg/String")
        bag.writer.write(connection, 5, text)
    with pytest.raises(
        BagError, match=r"topic /radar/b_scan, message 0: does not decode as navtech_msgs/msg/RadarBScanMsg"
    ):
        read_all(bag_path)


def test_a_scan_that_disagrees_with_its_configuration_is_refused(tmp_path: Path, scans):
    """The configuration says 3768 bins; a scan of 3000 bins in the same bag is refused naming both."""
    store = types.typestore()
    other = native_scans(1, bins=3000)[0]
    out = tmp_path / "geometry2"
    from tools.navtech_bag import _configuration

    with BagWriter(out) as bag:
        bag.write(
            "/radar_data/configuration_data",
            types.CONFIGURATION,
            1,
            _configuration(store, 1, 400, 3768, 0.0432, "typed"),
        )
        message, log = b_scan_message(store, other)
        bag.write("/radar_data/b_scan_msg", types.B_SCAN, log, message)
    with pytest.raises(
        BagError, match=r"message 0: the scan is 400 azimuths x 3000 range bins but its configuration .* 400 x 3768"
    ):
        read_all(out)


def test_a_corrupt_or_truncated_bag_is_refused(tmp_path: Path, navtech_bag: Path):
    mcap = next(navtech_bag.glob("*.mcap"))
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    with pytest.raises(BagError, match="truncated.mcap"):
        read_all(truncated)
    garbage = tmp_path / "garbage.db3"
    garbage.write_bytes(b"this is no sqlite database" * 100)
    with pytest.raises(BagError, match="garbage.db3 is not a readable bag"):
        read_all(garbage)
    from mcap.reader import make_reader

    with mcap.open("rb") as handle:
        chunk = make_reader(handle).get_summary().chunk_indexes[1]
    corrupt = tmp_path / "corrupt.mcap"
    data = bytearray(mcap.read_bytes())
    start = chunk.chunk_start_offset + 60  # inside the second chunk, over its message record's header
    data[start : start + 4000] = bytes(4000)
    corrupt.write_bytes(bytes(data))
    with pytest.raises(BagError, match=r"corrupt.mcap: topic /radar_data/b_scan_msg: the bag's index lists 3 messages"):
        read_all(corrupt)
    with pytest.raises(FileNotFoundError):
        read_all(tmp_path / "missing.mcap")


def test_a_message_of_absurd_size_is_refused_before_it_is_decoded(tmp_path: Path, monkeypatch, navtech_bag: Path):
    """A scan message larger than any radar's is refused naming it; the index check refuses an oversized MCAP chunk
    or sqlite3 row before anything is read (limits lowered here so that the bag stays small)."""
    import rafd.ros.reader as reader

    monkeypatch.setattr(reader, "MAX_MESSAGE_BYTES", 1_000_000)
    with pytest.raises(BagError, match=r"topic /radar_data/b_scan_msg, message 0: 1\d{6} bytes, more than 1000000"):
        read_all(navtech_bag)
    monkeypatch.undo()
    with pytest.raises(BagError, match=r"a chunk at offset \d+ holds \d+ bytes, more than 1000000"):
        reader.check_record_sizes(navtech_bag, limit=1_000_000)
    sqlite_bag = write_navtech_bag(tmp_path / "rows", native_scans(1), 0.0432, "sqlite3")
    with pytest.raises(BagError, match=r"topic /radar_data/b_scan_msg, the message logged at \d+ ns holds \d+ bytes"):
        reader.check_record_sizes(sqlite_bag, limit=1_000_000)


def test_an_image_of_absurd_size_is_refused_from_its_sizes(tmp_path: Path):
    """An Image claiming 400 x 400,000 pixels (a real sensor has at most 6848 bins) is refused from its width and
    height, before its data is used; a PNG likewise from its header."""
    store = types.typestore()
    huge = make(
        store, types.IMAGE, header=header(store, 1, "radar"), height=400, width=400_000, encoding="mono8", step=400_000
    )
    bag = _image_bag(tmp_path / "huge", [("/radar/scan", types.IMAGE, huge, 1)])
    with pytest.raises(BagError, match=r"message 0: image of 400000 x 400 .* is no radar scan"):
        read_all(bag)


def test_a_bag_copied_without_its_index_still_reads(tmp_path: Path, navtech_bag: Path):
    copy = tmp_path / "copy"
    shutil.copytree(navtech_bag, copy)
    assert len(read_all(copy)) == 3
