"""RINEX observation files as RTKLIB 2.4.3 reads them: event records, a 0.000 pseudorange, which code and Doppler."""
import gzip
import warnings

import numpy as np
import pytest

from lfgnss.rinex import _V2_EPOCH_RE, RinexWarning, load_obs
from lfgnss.solve import SAMPLE_OBS

from test_rinex import _rinex3


def _v2_epochs(n: int) -> tuple[list[str], list[list[str]]]:
    """The bundled RINEX 2 drive's header lines and its first ``n`` epochs' lines (C1 L1 S1 D1: one line a record)."""
    lines = gzip.decompress(SAMPLE_OBS.read_bytes()).decode().splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    starts = [i for i in range(end, len(lines)) if _V2_EPOCH_RE.match(lines[i])][:n + 1]
    return lines[:end], [lines[a:b] for a, b in zip(starts, starts[1:])]


def _load(path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        obs = load_obs(path, cache=False)
    return obs, [str(w.message) for w in caught if issubclass(w.category, RinexWarning)]


def _v3_with_event(path, types: dict[str, str], event: list[str]):
    """A 3-epoch RINEX 3 file (``_rinex3``) with the ``event`` lines before its second epoch; (Observations, notes)."""
    v3 = _rinex3(path, "3.04", types, n_epochs=3)
    lines = v3.read_text().splitlines()
    second = [i for i, ln in enumerate(lines) if ln.startswith(">")][1]
    lines[second:second] = event
    v3.write_text("\n".join(lines) + "\n")
    return _load(v3)


@pytest.mark.parametrize("event", [["                            4  2", "ANTENNA CHANGED".ljust(60) + "COMMENT",
                                    "SOME INFO".ljust(60) + "COMMENT"],
                                   ["                            2  0"],
                                   ["                            5  0"]], ids=["flag4", "flag2", "flag5"])
def test_a_rinex2_event_without_a_time_costs_no_epoch(tmp_path, event):
    """RINEX 2.11 lets an event line (flags 2-5) leave its time blank; it used to read as one record line too many
    and cost the epoch before it."""
    header, epochs = _v2_epochs(3)
    path = tmp_path / "e.obs"
    path.write_text("\n".join(header + epochs[0] + event + epochs[1] + epochs[2]) + "\n")
    obs, notes = _load(path)
    assert len(obs.time_gps_s) == 3 and not notes, notes
    plain = tmp_path / "p.obs"
    plain.write_text("\n".join(header + epochs[0] + epochs[1] + epochs[2]) + "\n")
    np.testing.assert_array_equal(obs.pr_m, load_obs(plain, cache=False).pr_m)


def test_rinex2_cycle_slip_records_are_skipped_whole(tmp_path):
    """A flag-6 epoch's records are laid out as an epoch's (satellite-id continuation lines, then the records):
    all of them are skipped, not read as an unreadable epoch line."""
    header, epochs = _v2_epochs(3)
    slips = [epochs[0][0][:28] + "6" + epochs[0][0][29:]] + epochs[0][1:]        # 19 satellites: two id lines
    path = tmp_path / "s.obs"
    path.write_text("\n".join(header + epochs[0] + slips + epochs[1] + epochs[2]) + "\n")
    obs, notes = _load(path)
    assert len(obs.time_gps_s) == 3 and not notes, notes


def _v2_in_types(epoch: list[str], types: list[str]) -> list[str]:
    """A bundled-drive epoch (C1 L1 S1 D1, one line a record) with each record's values laid out in ``types``
    (a type the drive lacks left blank)."""
    header_types = ["C1", "L1", "S1", "D1"]
    n_lines, n_id_lines = (len(types) + 4) // 5, (int(epoch[0][29:32]) + 11) // 12
    out = epoch[:n_id_lines]
    for record in epoch[n_id_lines:]:
        values = [record.ljust(80)[16 * k: 16 * k + 16] for k in range(4)]
        fields = "".join(values[header_types.index(t)] if t in header_types else " " * 16 for t in types)
        out += [fields[80 * k: 80 * k + 80].rstrip() for k in range(n_lines)]
    return out


@pytest.mark.parametrize("types", [["C1", "L1", "D1", "S1"], ["S1", "P2", "C1", "L2", "D1", "L1"]],
                         ids=["reordered", "two-lines-a-record"])
def test_observation_types_redefined_by_an_event_are_read_from_there(tmp_path, types):
    """A flag-4 event may bring a new '# / TYPES OF OBSERV': the epochs after it are read in its layout (the reading
    ended there, leaving them out; read with the header's types a Doppler had become a C/N0 of 464 dB-Hz)."""
    header, epochs = _v2_epochs(3)
    event = ["                            4  1", f"{len(types):6d}" + "".join(f"{t:>6s}" for t in types).ljust(54)
             + "# / TYPES OF OBSERV"]
    path = tmp_path / "t.obs"
    path.write_text("\n".join(header + epochs[0] + event + _v2_in_types(epochs[1], types)
                              + _v2_in_types(epochs[2], types)) + "\n")
    obs, notes = _load(path)
    plain = tmp_path / "p.obs"
    plain.write_text("\n".join(header + epochs[0] + epochs[1] + epochs[2]) + "\n")
    ref = load_obs(plain, cache=False)
    assert not notes and len(obs.time_gps_s) == 3, notes
    for name in ("pr_m", "cn0_dbhz", "doppler_hz"):
        np.testing.assert_array_equal(getattr(obs, name), getattr(ref, name))


def test_types_an_event_drops_are_missing_from_there_with_a_note(tmp_path):
    header, epochs = _v2_epochs(3)
    types = ["C1", "L1", "D1"]
    event = ["                            4  1", "     3    C1    L1    D1".ljust(60) + "# / TYPES OF OBSERV"]
    path = tmp_path / "d.obs"
    path.write_text("\n".join(header + epochs[0] + event + _v2_in_types(epochs[1], types)
                              + _v2_in_types(epochs[2], types)) + "\n")
    obs, notes = _load(path)
    assert len(obs.time_gps_s) == 3
    assert np.isfinite(obs.cn0_dbhz[0]).any() and np.isnan(obs.cn0_dbhz[1:]).all()
    assert np.isfinite(obs.pr_m[1:]).any() and np.isfinite(obs.doppler_hz[1:]).any()
    assert any(f"{path}:{len(header) + len(epochs[0]) + 1}: the event here redefines the observation types without "
               f"S1 of GR: read as missing from here on" in n for n in notes), notes


def _v3_redefined(path, event_types: str | None, count: int | None = None):
    """A 3-epoch RINEX 3 file of G01-G03 with types C1C D1C S1C, an event before its second epoch giving
    ``event_types`` (declaring ``count`` of them), the later epochs written in those types: C1C 2e7 + 1000 s,
    D1C 200, S1C 40, C1W 9 m more than C1C."""
    head = ["     3.04           OBSERVATION DATA    G                   RINEX VERSION / TYPE",
            "G    3 C1C D1C S1C".ljust(60) + "SYS / # / OBS TYPES",
            "  2020     6     3     3     2    9.0000000     GPS".ljust(60) + "TIME OF FIRST OBS",
            " " * 60 + "END OF HEADER"]
    body = []
    for e in range(3):
        body.append(f"> 2020 06 03 03 02{9.0 + e:11.7f}  0  3")
        if e == 1 and event_types is not None:
            n = len(event_types.split()) if count is None else count
            body[-1:-1] = ["> 2020 06 03 03 02  9.5000000  4  1", f"G  {n:3d} {event_types}".ljust(60)
                           + "SYS / # / OBS TYPES"]
        names = (event_types if e and event_types is not None else "C1C D1C S1C").split()
        for s in (1, 2, 3):
            value = {"C1C": 2e7 + 1000 * s, "C1W": 2e7 + 1000 * s + 9, "D1C": 100.0 + 100 * (e > 0),
                     "S1C": 45.0 - 5 * (e > 0)}
            body.append(f"G{s:02d}" + "".join(f"{value[n]:14.3f}  " for n in names).rstrip())
    path.write_text("\n".join(head + body) + "\n")
    return _load(path)


def test_rinex3_types_redefined_by_an_event_are_read_from_there(tmp_path):
    obs, notes = _v3_redefined(tmp_path / "r.rnx", "S1C C1W C1C D1C")
    assert not notes and len(obs.time_gps_s) == 3, notes
    np.testing.assert_array_equal(obs.pr_m, np.tile(2e7 + 1000 * np.arange(1, 4), (3, 1)))
    np.testing.assert_array_equal(obs.doppler_hz[:, 0], [100, 200, 200])
    np.testing.assert_array_equal(obs.cn0_dbhz[:, 0], [45, 40, 40])
    obs, notes = _v3_redefined(tmp_path / "d.rnx", "C1C D1C")
    assert len(obs.time_gps_s) == 3 and np.isnan(obs.cn0_dbhz[1:]).all()
    assert any("redefines the observation types without S1C of G: read as missing" in n for n in notes), notes
    # the header's code gone: no pseudorange of G from there (C1W, another signal, does not stand in)
    obs, notes = _v3_redefined(tmp_path / "w.rnx", "C1W D1C S1C")
    assert obs.codes == {"G": "C1C"} and np.isfinite(obs.pr_m[0]).all() and np.isnan(obs.pr_m[1:]).all()
    assert any("without C1C of G: read as missing" in n for n in notes), notes


@pytest.mark.parametrize("types, count", [("C1C S1C D1C", 4), ("", 0)], ids=["miscounted", "none"])
def test_types_an_event_gives_unreadably_end_the_reading_there(tmp_path, types, count):
    """A count that is not the number of types listed, or no type at all (review: that ended the reading silently)."""
    obs, notes = _v3_redefined(tmp_path / "u.rnx", types, count=count)
    assert len(obs.time_gps_s) == 1
    assert any(f"{tmp_path / 'u.rnx'}:9: the event here redefines the observation types (SYS / # / OBS TYPES) in "
               f"lines that cannot be read" in n and "left out" in n for n in notes), notes


def test_the_headers_own_types_repeated_by_an_event_change_nothing(tmp_path):
    """A spliced file repeats its header in a flag-4 event: the same types, so the reading goes on (RTKLIB's too)."""
    header, epochs = _v2_epochs(3)
    types = next(h for h in header if "TYPES OF OBSERV" in h)
    path = tmp_path / "same.obs"
    path.write_text("\n".join(header + epochs[0] + ["                            4  1", types] + epochs[1] + epochs[2])
                    + "\n")
    obs, notes = _load(path)
    assert len(obs.time_gps_s) == 3 and not notes, notes
    obs, notes = _v3_with_event(tmp_path / "same.rnx", {"G": "C1C D1C S1C", "E": "C1C S1C"}, [
        "> 2020 06 03 03 02  9.5000000  4  1", "G    3 C1C D1C S1C".ljust(60) + "SYS / # / OBS TYPES"])
    assert len(obs.time_gps_s) == 3 and not notes, notes
    # a system the header lacks (or SBAS) shifts no GPS column: each record line names its system
    obs, notes = _v3_with_event(tmp_path / "new.rnx", {"G": "C1C D1C S1C"}, [
        "> 2020 06 03 03 02  9.5000000  4  2", "E    2 C1C S1C".ljust(60) + "SYS / # / OBS TYPES",
        "S    2 C1C S1C".ljust(60) + "SYS / # / OBS TYPES"])
    assert len(obs.time_gps_s) == 3 and not notes, notes


def test_a_rinex3_event_without_a_time_is_no_unreadable_epoch_line(tmp_path):
    obs, notes = _v3_with_event(tmp_path / "e.rnx", {"G": "C1C S1C"},
                                [">" + " " * 30 + "4  1", "ANTENNA CHANGED".ljust(60) + "COMMENT"])
    assert len(obs.time_gps_s) == 3 and not notes, notes


def test_a_pseudorange_of_zero_is_missing(tmp_path):
    """RTKLIB reads 0.000 as no code: in RINEX 2 P1 stands in (as for a blank C1), in RINEX 3 the satellite has no
    pseudorange that epoch (it was kept as a measurement of 0 m)."""
    header, epochs = _v2_epochs(2)
    header = [("     5    C1    L1    S1    D1    P1".ljust(60) + "# / TYPES OF OBSERV") if "TYPES OF OBSERV" in h
              else h for h in header]
    first = [epochs[0][0], epochs[0][1]] + [r.ljust(64) + r[:16] for r in epochs[0][2:]]   # P1 = C1
    first[2] = "        0.000  " + first[2][15:]                                              # C1 of the first sat
    second = [epochs[1][0], epochs[1][1]] + [r.ljust(64) + r[:16] for r in epochs[1][2:]]
    path = tmp_path / "z.obs"
    path.write_text("\n".join(header + first + second) + "\n")
    obs, notes = _load(path)
    sv = first[0][32:35].replace(" ", "G")
    assert obs.pr_m[0, list(obs.sv).index(sv)] == pytest.approx(float(epochs[0][2][:14]))      # P1's value
    assert any("C1 blank (or 0), P1 used instead" in n for n in notes), notes

    v3 = _rinex3(tmp_path / "z.rnx", "3.04", {"G": "C1C S1C"}, n_epochs=2)
    v3.write_text(v3.read_text().replace("G01  20001000.000", "G01         0.000", 1))
    obs = load_obs(v3, cache=False)
    assert np.isnan(obs.pr_m[0, 0]) and obs.pr_m[1, 0] == 20001000.0


@pytest.mark.parametrize("system, types, code", [
    ("G", "C1W C1P S1C", "C1P"), ("E", "C1X C1B S1B", "C1B"), ("J", "C1X C1L S1L", "C1L"), ("J", "C1S S1S", "C1S"),
    ("C", "C2X C2Q S2Q", "C2Q"), ("R", "C1P C1C S1C", "C1C"),
])
def test_the_code_rtklib_would_take(tmp_path, system, types, code):
    """RTKLIB 2.4.3 b34's code priorities (codepris: GPS CPYWMNSL, GLONASS CPABX, Galileo CABXZ, QZSS CLSXZ,
    BeiDou IQXDPAN); QZSS's L1C (C1L, C1S) is read as GPS's C1X is."""
    obs = load_obs(_rinex3(tmp_path / "c.rnx", "3.04", {system: types}), cache=False)
    assert obs.codes == {system: code}
    assert obs.pr_m[0, 1] == 2e7 + 2000 + types.split().index(code)


def test_a_code_without_its_own_doppler_takes_its_bands(tmp_path):
    """GPS C1W (semi-codeless P(Y)) has no D1W in a file that has D1C: the carrier's Doppler is one, so D1C is read;
    of several, the one of the most preferred code (D1C before D1X, whatever the header's order)."""
    obs = load_obs(_rinex3(tmp_path / "d.rnx", "3.04", {"G": "C1W D1C S1W"}), cache=False)
    assert obs.codes == {"G": "C1W"} and np.all(obs.doppler_hz == 100.0)
    path = _rinex3(tmp_path / "x.rnx", "3.04", {"G": "C1W D1X D1C S1W"})
    lines = [ln[:19] + f"{200.0:14.3f}" + ln[33:] if ln.startswith("G") else ln       # D1X's values: 200
             for ln in path.read_text().splitlines()]
    path.write_text("\n".join(lines) + "\n")
    obs = load_obs(path, cache=False)
    assert obs.codes == {"G": "C1W"} and obs.doppler_hz[0, 0] == 100.0          # D1C's, not D1X's 200


def test_the_georinex_engine_refuses_redefined_types_and_reads_a_satellite_without_pseudoranges(tmp_path):
    """Review: engine='georinex' read the header's columns after an event that redefines them (a C/N0 of 20.861 as the
    pseudorange, with no note), and a satellite with C/N0 but never a pseudorange was an IndexError."""
    from lfgnss.errors import RinexError

    header, epochs = _v2_epochs(3)
    types = ["C1", "L1", "D1", "S1"]
    event = ["                            4  1", "     4    C1    L1    D1    S1".ljust(60) + "# / TYPES OF OBSERV"]
    path = tmp_path / "t.obs"
    path.write_text("\n".join(header + epochs[0] + event + _v2_in_types(epochs[1], types)) + "\n")
    with pytest.raises(RinexError, match=rf"^{path}:{len(header) + len(epochs[0]) + 1}: an event redefines the "
                                         r"observation types here, which engine='georinex' cannot read"):
        load_obs(path, cache=False, engine="georinex")
    blank = tmp_path / "blank.rnx"
    blank.write_text("\n".join([
        "     3.04           OBSERVATION DATA    G                   RINEX VERSION / TYPE",
        "G    2 C1C S1C".ljust(60) + "SYS / # / OBS TYPES",
        "  2020     6     3     3     2    9.0000000     GPS".ljust(60) + "TIME OF FIRST OBS",
        " " * 60 + "END OF HEADER",
        "> 2020 06 03 03 02  9.0000000  0  2", "G01  20008600.000          20.860", "G02                        20.870",
        "> 2020 06 03 03 02 10.0000000  0  2", "G01  20008601.000          20.861",
        "G02                        20.871"]) + "\n")
    obs = load_obs(blank, cache=False, engine="georinex")
    ours = load_obs(blank, cache=False)
    assert list(obs.sv) == list(ours.sv) == ["G01"]
    np.testing.assert_array_equal(obs.cn0_dbhz, ours.cn0_dbhz)


def test_a_redefinition_notes_only_types_of_constellations_in_the_file(tmp_path):
    """Review: a GPS + GLONASS RINEX 2 file whose event dropped C2 was told 'without C2', lfgnss's BeiDou code
    there, though the file has no BeiDou satellite and every value was read."""
    header, epochs = _v2_epochs(3)
    wide = ["C1", "L1", "S1", "D1", "C2"]
    header = [("     5    C1    L1    S1    D1    C2".ljust(60) + "# / TYPES OF OBSERV") if "TYPES OF OBSERV" in h
              else h for h in header]
    event = ["                            4  1", "     4    C1    L1    S1    D1".ljust(60) + "# / TYPES OF OBSERV"]
    path = tmp_path / "gr.obs"
    path.write_text("\n".join(header + _v2_in_types(epochs[0], wide) + event + epochs[1] + epochs[2]) + "\n")
    obs, notes = _load(path)
    assert len(obs.time_gps_s) == 3 and not notes, notes


def test_a_rinex3_event_may_add_a_constellation_the_header_lacks(tmp_path):
    """Review: a GPS header, then an event giving GLONASS its types: the GLONASS records after it were skipped with
    'no SYS / # / OBS TYPES header line for R' (RTKLIB reads them); those before it have no types and are skipped."""
    head = ["     3.04           OBSERVATION DATA    M                   RINEX VERSION / TYPE",
            "G    2 C1C S1C".ljust(60) + "SYS / # / OBS TYPES",
            "  2020     6     3     3     2    9.0000000     GPS".ljust(60) + "TIME OF FIRST OBS",
            " " * 60 + "END OF HEADER"]
    body = ["> 2020 06 03 03 02  9.0000000  0  2", "G01  20001000.000          45.000",
            "R01  21001000.000          41.000",
            "> 2020 06 03 03 02  9.5000000  4  1", "R    2 S1C C1C".ljust(60) + "SYS / # / OBS TYPES"]
    for e in (1, 2):
        body += [f"> 2020 06 03 03 02 {9 + e:2d}.0000000  0  2", f"G01  {20001000 + e:12d}.000          45.000",
                 f"R01          42.000  {21001000 + e:12d}.000"]
    path = tmp_path / "add.rnx"
    path.write_text("\n".join(head + body) + "\n")
    obs, notes = _load(path)
    assert list(obs.sv) == ["G01", "R01"] and obs.codes == {"G": "C1C", "R": "C1C"}
    np.testing.assert_array_equal(obs.pr_m[:, 1], [np.nan, 21001001.0, 21001002.0])
    np.testing.assert_array_equal(obs.cn0_dbhz[:, 1], [np.nan, 42.0, 42.0])
    np.testing.assert_array_equal(obs.pr_m[:, 0], [20001000.0, 20001001.0, 20001002.0])
    assert any(f"{path}:7: 1 record(s) of R before the event on line 8 gives their observation types" in n
               for n in notes), notes


def test_a_constellation_added_after_another_redefinition_is_read(tmp_path):
    """Review: GPS's types redefined, then GLONASS added by a later event: a KeyError (its early records sat in a piece
    whose types had no R)."""
    text = "\n".join([
        "     3.04           OBSERVATION DATA    M                   RINEX VERSION / TYPE",
        "G    3 C1C D1C S1C".ljust(60) + "SYS / # / OBS TYPES",
        "  2020     6     3     3     2    9.0000000     GPS".ljust(60) + "TIME OF FIRST OBS", " " * 60 + "END OF HEADER",
        "> 2020 06 03 03 02  9.0000000  0  2", "G01  20008600.000       -2914.000          20.860",
        "R05  20009000.100       -2910.000          20.900",
        "> 2020 06 03 03 02  9.5000000  4  1", "G    3 S1C C1C D1C".ljust(60) + "SYS / # / OBS TYPES",
        "> 2020 06 03 03 02 10.0000000  0  2", "G01        20.861    20008601.000       -2913.990",
        "R05  20009001.100       -2909.990          20.901",
        "> 2020 06 03 03 02 10.5000000  4  1", "R    3 C1C D1C S1C".ljust(60) + "SYS / # / OBS TYPES",
        "> 2020 06 03 03 02 11.0000000  0  2", "G01        20.862    20008602.000       -2913.980",
        "R05  20009002.100       -2909.980          20.902"]) + "\n"
    path = tmp_path / "later.rnx"
    path.write_text(text)
    obs, notes = _load(path)
    np.testing.assert_array_equal(obs.pr_m, [[20008600.0, np.nan], [20008601.0, np.nan], [20008602.0, 20009002.1]])
    np.testing.assert_array_equal(obs.cn0_dbhz[:, 0], [20.86, 20.861, 20.862])
    assert any(f"{path}:7: 2 record(s) of R before the event on line 13" in n for n in notes), notes
