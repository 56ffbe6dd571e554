#!/usr/bin/env python3
"""Fails if a Catch2 TEST_CASE name under test/ cannot be a CTest test name.

catch_discover_tests makes every TEST_CASE a CTest test named after it. CTest cuts a name at
';' (a CMake list separator): the test then runs the cut name, which matches no TEST_CASE, and
"passes" without running anything. That hid a failing bridge test for a whole stop.
Usage: check_test_names.py TEST_DIR
"""
import pathlib
import re
import sys

# TEST_CASE( then one or more adjacent string literals (the name may be split over lines).
NAME = re.compile(r'TEST_CASE\s*\(\s*((?:"(?:[^"\\]|\\.)*"\s*)+)')
LITERAL = re.compile(r'"((?:[^"\\]|\\.)*)"')


def main() -> int:
    root = pathlib.Path(sys.argv[1])
    bad, count = [], 0
    for path in sorted(root.rglob("*.cpp")):
        text = path.read_text(errors="replace")
        for m in NAME.finditer(text):
            name = "".join(LITERAL.findall(m.group(1)))
            count += 1
            if ";" in name:
                line = text.count("\n", 0, m.start()) + 1
                bad.append(f"{path}:{line}: TEST_CASE name has ';' (CTest cuts it there): {name}")
    for b in bad:
        print(b)
    print(f"{count} TEST_CASE names checked, {len(bad)} with ';'")
    return 1 if bad or count == 0 else 0


if __name__ == "__main__":
    sys.exit(main())
