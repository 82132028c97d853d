"""The lines the `blender -b` test scripts write for their tests to read (``say``): one
write a line, since Blender's Python writes stdout through and Ctrl-C's message once
landed between print()'s pieces ("SECONDS", then the message, then the number)."""

import io

from fixtures.blender.output import say


class Writes(io.StringIO):
    """A stdout that records every write, as a write-through stdout would send them."""

    def __init__(self):
        super().__init__()
        self.writes = []

    def write(self, text):
        self.writes.append(text)
        return super().write(text)


def test_a_line_goes_out_in_one_write_so_blenders_messages_cannot_tear_it(monkeypatch):
    out = Writes()
    monkeypatch.setattr("sys.stdout", out)
    say("SECONDS", 0.0023)
    say("OPEN", None)
    assert out.writes == ["SECONDS 0.0023\n", "OPEN None\n"]
