"""tools/readme_numbers.py: which tokens count as numbers, and what is reported missing."""

from scriptload import load_script

rn = load_script("tools/readme_numbers.py")

TEXT = ("TLR 0.69 -> 0.51 m, zone C p95 1.46 -> 0.84 m; 1.3-1.4x faster, 2^-24 and e^-87, "
        "1e-6 and 5.8e-8; Figs. 8-9, eq. (19)-(22); JP1-JP3 at 2026-11-25; x1.6; 0.50 m; 105650 rows.")


def test_number_tokens_of_a_fixed_string():
    assert rn.numbers(TEXT) == [
        "0.69", "0.51", "95", "1.46", "0.84", "1.3", "1.4", "2", "24", "87", "1e-6", "5.8e-8", "8", "9",
        "19", "22", "1", "3", "2026", "11", "25", "1.6", "0.50", "105650"]


def test_missing_fewer_and_out_of_order():
    old = "a 0.51 m and 2.15 m\nb 4.27 -> 0.80 m\nc 0.51 m\n"
    new = {"docs/x.md": "0.80 then 4.27, and 0.51 before 2.15"}
    missing, fewer = rn.check(old, new)
    assert missing == []
    assert fewer == {"0.51": (2, 1)}
    assert rn.out_of_order(old, new) == [(2, "b 4.27 -> 0.80 m")]
    missing, _ = rn.check(old + "d 0.5 m\n", new)  # 0.5 is not 0.51
    assert [(i, tok) for i, tok, _ in missing] == [(4, "0.5")]
