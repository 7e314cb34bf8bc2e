"""Reading .fap streams: the real files, and one test per real-world variant."""

from __future__ import annotations

import numpy as np
import pytest

from fae.io.fap import Expression, FapFormatError, FapParser, Viseme, read_fap


def mask_line(faps, tokens=68, lead=""):
    bits = ["1" if n in faps else "0" for n in range(1, 69)]
    if tokens == 69:
        bits = [lead or "0"] + bits
    return " ".join(bits)


HEAD_MASK = mask_line({3, 19, 20, 48})


def small_fap(header="2.1 test 25 3", numbers=(0, 1, 2), eol="\n", sep=" "):
    lines = [header]
    for k, n in enumerate(numbers):
        lines.append(HEAD_MASK)
        lines.append(f"{n} {100 + k} {-5 * k} 7 {8500 - k}")
    return eol.join(line.replace(" ", sep) for line in lines) + eol


def write(tmp_path, text, name="s.fap"):
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8") if isinstance(text, str) else text)
    return path


def frames_of(path):
    stream = read_fap(path)
    return stream, list(stream)


def values_of(frames):
    return np.array([f.values for f in frames])


# ---- the real files ----------------------------------------------------------------------
def test_every_shared_fap_file_parses(shared_data):
    files = sorted((shared_data / "fap").glob("*.fap"))
    assert len(files) >= 9
    for path in files:
        stream, frames = frames_of(path)
        assert stream.header.version == "2.1" and stream.header.fps == 25.0
        assert len(frames) == stream.header.declared_frame_count == stream.frame_count
        assert [f.number for f in frames] == list(range(len(frames)))
        assert stream.warnings == []
        used = np.any([f.mask for f in frames], axis=0)
        assert used[2] and used[47] and not used[0] and not used[1]  # open_jaw, head_pitch; no visemes
        head = values_of(frames)[:, 47:50]
        assert 1000 < np.abs(head).max() < 10000  # head rotations up to ~8500 AU, as documented


def test_xface_anger_first_frames_decode_token_by_token(shared_data):
    lines = (shared_data / "fap" / "xface_anger.fap").read_text().splitlines()
    stream, frames = frames_of(shared_data / "fap" / "xface_anger.fap")
    for k in (0, 1, 50):
        mask_tokens = lines[1 + 2 * k].split()
        value_tokens = lines[2 + 2 * k].split()
        assert int(value_tokens[0]) == frames[k].number == k
        masked = [i for i, t in enumerate(mask_tokens) if t == "1"]
        assert np.array_equal(np.flatnonzero(frames[k].mask), masked)
        assert frames[k].values[masked].tolist() == [float(v) for v in value_tokens[1:]]
        assert not frames[k].values[~frames[k].mask].any()


def test_shipped_streams_read_without_warnings(repo_root):
    files = sorted((repo_root / "fap_streams").glob("*.fap"))
    assert {p.name for p in files} >= {"expressions.fap", "visemes.fap", "eyes_head.fap", "all_faps_sweep.fap"}
    for path in files:
        stream, frames = frames_of(path)
        assert stream.header.version == "2.1" and stream.warnings == [] and frames


# ---- streaming -------------------------------------------------------------------------------
def test_header_is_available_before_iterating_and_frames_stream(tmp_path):
    text = small_fap() + HEAD_MASK + "\n3 1 2 3 nan\n"
    stream = read_fap(write(tmp_path, text))
    assert stream.header.name == "test" and stream.header.declared_frame_count == 3
    frames = iter(stream)
    assert [next(frames).number for _ in range(3)] == [0, 1, 2]  # yielded before the bad line is read
    with pytest.raises(FapFormatError) as info:
        next(frames)
    assert info.value.line == 9 and info.value.token == "nan"
    assert str(info.value) == f"{tmp_path / 's.fap'}:9: token 'nan': expected a value for FAP 48 (a finite decimal number)"


def test_parser_is_push_style(tmp_path):
    parser = FapParser("socket")
    assert parser.feed_line("2.1 live 30 0\r\n", 1) is None and parser.header.fps == 30.0
    assert parser.feed_line(HEAD_MASK + "\n", 2) is None
    frame = parser.feed_line("0 1 2 3 4\n", 3)
    assert frame.number == 0 and frame.values[[2, 18, 19, 47]].tolist() == [1, 2, 3, 4]
    parser.finish()
    assert any("declares 0 frames" in w for w in parser.warnings)


# ---- one test per variant ------------------------------------------------------------------
def test_versions_2_0_2_1_2_2_read_alike_and_2_0_warns(tmp_path):
    results = {}
    for version in ("2.0", "2.1", "2.2"):
        stream, frames = frames_of(write(tmp_path, small_fap(f"{version} v 25 3"), f"{version}.fap"))
        results[version] = (values_of(frames), stream.warnings)
    assert np.array_equal(results["2.0"][0], results["2.1"][0]) and np.array_equal(results["2.2"][0], results["2.1"][0])
    assert results["2.1"][1] == [] and results["2.2"][1] == []
    assert len(results["2.0"][1]) == 1 and "2.0" in results["2.0"][1][0]
    with pytest.raises(FapFormatError, match="token '3.0': expected a .fap version"):
        list(read_fap(write(tmp_path, small_fap("3.0 v 25 3"))))


def test_crlf_tabs_blank_lines_and_comments_give_the_same_frames(tmp_path):
    _, plain = frames_of(write(tmp_path, small_fap(), "plain.fap"))
    _, crlf = frames_of(write(tmp_path, small_fap(eol="\r\n"), "crlf.fap"))
    _, tabs = frames_of(write(tmp_path, small_fap(sep="\t"), "tabs.fap"))
    lines = small_fap().splitlines()
    commented = ["# made by hand", "", lines[0], "#mask next", lines[1], "", "   # indented comment",
                 lines[2] + "   # inline comment", *lines[3:5], "\t", *lines[5:], "# end"]
    _, noisy = frames_of(write(tmp_path, "\ufeff" + "\n".join(commented), "noisy.fap"))
    for other in (crlf, tabs, noisy):
        assert other == plain


def test_69_token_masks(tmp_path):
    lines = small_fap().splitlines()
    _, plain = frames_of(write(tmp_path, small_fap(), "plain.fap"))
    leading = [lines[0]] + [mask_line({3, 19, 20, 48}, 69) if i % 2 == 0 else line
                            for i, line in enumerate(lines[1:])]
    stream, frames = frames_of(write(tmp_path, "\n".join(leading), "lead.fap"))
    assert frames == plain and len(stream.warnings) == 1 and "69-token" in stream.warnings[0]
    # A leading 1 cannot be an unused slot: then the extra slot must be the trailing one.
    stream, (frame,) = frames_of(write(tmp_path, f"2.1 t 25 1\n{mask_line({1, 3})} 0\n0 5 120\n", "trail.fap"))
    assert frame.viseme == Viseme(5, 0, 63, 0) and frame.values[2] == 120 and "trailing" in stream.warnings[0]
    bad = [lines[0], "1 " + mask_line({3, 68}), "0 1 2 3"]
    with pytest.raises(FapFormatError, match=r":2: token '1': expected 0 in the unused"):
        list(read_fap(write(tmp_path, "\n".join(bad), "bad.fap")))
    with pytest.raises(FapFormatError, match="68 \\(or 69\\) tokens"):
        list(read_fap(write(tmp_path, "\n".join([lines[0], lines[1] + " 0 0", lines[2]]), "70.fap")))


def test_frame_numbers_from_1_and_with_gaps(tmp_path):
    stream, frames = frames_of(write(tmp_path, small_fap(numbers=(1, 2, 3))))
    assert [f.number for f in frames] == [1, 2, 3] and stream.warnings == []
    stream, frames = frames_of(write(tmp_path, small_fap(numbers=(0, 5, 6))))
    assert [f.number for f in frames] == [0, 5, 6]
    assert len(stream.warnings) == 1 and "skip from 0 to 5" in stream.warnings[0]
    with pytest.raises(FapFormatError, match="token '1': expected a frame number greater than the previous one"):
        list(read_fap(write(tmp_path, small_fap(numbers=(0, 2, 1)))))


def test_names_with_spaces_and_integer_or_float_fps(tmp_path):
    stream = read_fap(write(tmp_path, small_fap(r"2.1 C:\My Files\take  2 29.97 3")))
    assert stream.header.name == r"C:\My Files\take  2" and stream.header.fps == 29.97
    stream = read_fap(write(tmp_path, small_fap("2.1 x 30 3")))
    assert stream.header.fps == 30.0
    stream = read_fap(write(tmp_path, small_fap("2.1 25 3")))
    assert stream.header.name == "" and "no name" in stream.warnings[0]
    for header, token in (("2.1 x 0 3", "0"), ("2.1 x -25 3", "-25"), ("2.1 x inf 3", "inf"), ("2.1 x 25 3.5", "3.5")):
        with pytest.raises(FapFormatError, match=f"token '{token}'"):
            read_fap(write(tmp_path, small_fap(header)))


def test_declared_frame_count_that_disagrees_warns(tmp_path):
    stream, frames = frames_of(write(tmp_path, small_fap("2.1 x 25 10")))
    assert len(frames) == 3 and stream.frame_count == 3
    assert stream.warnings == [f"{tmp_path / 's.fap'}: header declares 10 frames, the body has 3"]


def _highlevel_file(tmp_path, values_line, faps=(1, 3)):
    return write(tmp_path, f"2.1 hl 25 1\n{mask_line(set(faps))}\n{values_line}\n")


def test_fap1_as_one_token_or_four_viseme_fields(tmp_path):
    _, (frame,) = frames_of(_highlevel_file(tmp_path, "0 10 120"))
    assert frame.viseme == Viseme(10, 0, 63, 0) and frame.values[0] == 10 and frame.values[2] == 120
    _, (frame,) = frames_of(_highlevel_file(tmp_path, "0 10 1 40 1 120"))
    assert frame.viseme == Viseme(10, 1, 40, 1) and frame.values[0] == 10 and frame.values[2] == 120
    stream, (frame,) = frames_of(_highlevel_file(tmp_path, "0 2500 120"))
    assert frame.viseme is None and frame.values[0] == 2500 and "not a viseme code" in stream.warnings[0]
    with pytest.raises(FapFormatError, match="2 or 5 values after the frame number"):
        list(read_fap(_highlevel_file(tmp_path, "0 10 1 40 120")))
    with pytest.raises(FapFormatError, match="token '15': expected viseme_select2"):
        list(read_fap(_highlevel_file(tmp_path, "0 10 15 40 1 120")))


def test_fap2_as_one_token_or_six_expression_fields_with_and_without_fap1(tmp_path):
    _, (frame,) = frames_of(_highlevel_file(tmp_path, "0 4 120", faps=(2, 3)))
    assert frame.expression == Expression(4, 63, 0, 0, 0, 0) and frame.viseme is None
    _, (frame,) = frames_of(_highlevel_file(tmp_path, "0 1 50 3 20 1 0 120", faps=(2, 3)))
    assert frame.expression == Expression(1, 50, 3, 20, 1, 0) and frame.values[1] == 1
    for line, viseme, expression in (
            ("0 7 4 120", Viseme(7, 0, 63, 0), Expression(4, 63, 0, 0, 0, 0)),
            ("0 7 2 30 0 4 120", Viseme(7, 2, 30, 0), Expression(4, 63, 0, 0, 0, 0)),
            ("0 7 1 50 3 20 1 0 120", Viseme(7, 0, 63, 0), Expression(1, 50, 3, 20, 1, 0)),
            ("0 7 2 30 0 1 50 3 20 1 0 120", Viseme(7, 2, 30, 0), Expression(1, 50, 3, 20, 1, 0))):
        _, (frame,) = frames_of(_highlevel_file(tmp_path, line, faps=(1, 2, 3)))
        assert (frame.viseme, frame.expression, frame.values[2]) == (viseme, expression, 120), line
    with pytest.raises(FapFormatError, match="3 or 6 or 8 or 11 values"):
        list(read_fap(_highlevel_file(tmp_path, "0 7 2 30 4 120", faps=(1, 2, 3))))


def test_truncated_last_frame_is_dropped_with_a_warning(tmp_path):
    stream, frames = frames_of(write(tmp_path, small_fap() + HEAD_MASK + "\n"))
    assert len(frames) == 3 and any("without a values line" in w for w in stream.warnings)


@pytest.mark.parametrize("body, line, token, expected", [
    ("", 0, None, "header line"),
    ("# only a comment\n\n", 0, None, "header line"),
    ("\x00\x01\x02garbage\xff\xfe\n", 1, "\x00\x01\x02garbage\xff\xfe", "header line"),
    ("2.1 x 25 1\n" + HEAD_MASK.replace("0", "2", 1) + "\n0 1 2 3 4\n", 2, "2", "mask bit"),
    ("2.1 x 25 1\n" + HEAD_MASK + "\n0 1 2 3\n", 3, None, "4 values after the frame number"),
    ("2.1 x 25 1\n" + HEAD_MASK + "\n0 1 2 inf 4\n", 3, "inf", "finite decimal number"),
    ("2.1 x 25 1\n" + HEAD_MASK + "\n0 1 2 1e999 4\n", 3, "1e999", "finite decimal number"),
    ("2.1 x 25 1\n" + HEAD_MASK + "\n0 1 2 0x10 4\n", 3, "0x10", "finite decimal number"),
    ("2.1 x 25 1\n" + HEAD_MASK + "\n-1 1 2 3 4\n", 3, "-1", "the frame number"),
    ("2.1 x 25 1\n" + HEAD_MASK + "\n" + "9" * 5000 + " 1 2 3 4\n", 3, "9" * 5000, "the frame number"),
    ("2.1 x 25 1\r" + HEAD_MASK + "\r0 1 2 3 4\r", 1, None, "LF or CRLF"),
])
def test_what_cannot_be_understood_is_rejected_with_file_line_token(tmp_path, body, line, token, expected):
    path = write(tmp_path, body.encode("latin-1"))
    with pytest.raises(FapFormatError) as info:
        list(read_fap(path))
    error = info.value
    assert (error.path, error.line, error.token) == (str(path), line, token)
    assert expected in error.expected and str(path) in str(error)


def test_bad_utf8_in_the_name_is_read_as_latin1_with_a_warning(tmp_path):
    path = write(tmp_path, small_fap("2.1 Gr\xfc\xdfe 25 3").encode("latin-1"))
    stream, frames = frames_of(path)
    assert stream.header.name == "Grüße" and len(frames) == 3 and "Latin-1" in stream.warnings[0]


def test_huge_but_finite_values_are_read(tmp_path):
    text = "2.1 x 25 1\n" + HEAD_MASK + "\n0 1e300 -99999999999999999999999 3.5 4\n"
    _, (frame,) = frames_of(write(tmp_path, text))
    assert frame.values[[2, 18, 19, 47]].tolist() == [1e300, -1e23, 3.5, 4.0]


def test_missing_file_and_directory_raise_format_errors(tmp_path):
    with pytest.raises(FapFormatError, match="no-such.fap: expected a readable .fap file"):
        read_fap(tmp_path / "no-such.fap")
    with pytest.raises(FapFormatError):
        read_fap(tmp_path)


def test_the_parser_refuses_an_overlong_line_itself_naming_the_line():
    """A caller that feeds lines without bounding them (FapParser is public) still cannot
    make it split a 50 MB line: the line is refused by its length, before any token."""
    parser = FapParser("socket", max_line=4096)
    parser.feed_line("2.1 test 25 3", 1)
    with pytest.raises(FapFormatError, match=r"socket:2: expected a line of at most 4096 characters, got 50000000"):
        parser.feed_line("0 " * 25_000_000, 2)
    assert FapParser("x").max_line == 65536  # the file reader's own bound


@pytest.mark.parametrize("header, line, token", [
    ("2.1 test ２５ 3", None, "２５"),                 # fullwidth fps
    ("2.1 test 25 ٣", None, "٣"),                     # Arabic-Indic frame count
    ("2.1 test 25 3", "１２３ 100 0 7 8500", "１２３"),   # fullwidth frame number
    ("2.1 test 25 3", "0 １００ 0 7 8500", "１００"),     # fullwidth value
])
def test_only_ascii_digits_are_numbers(header, line, token):
    parser = FapParser("s.fap")
    with pytest.raises(FapFormatError) as info:
        parser.feed_line(header, 1)
        parser.feed_line(HEAD_MASK, 2)
        parser.feed_line(line, 3)
    assert info.value.token == token and "s.fap:" in str(info.value)
