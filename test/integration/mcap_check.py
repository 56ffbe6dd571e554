#!/usr/bin/python3
"""An independent MCAP reader for the tests of `lcmx log export --format mcap`.

Written from the MCAP specification (https://mcap.dev/spec), sharing no code with lcmx's
writer. Reads every record of FILE front to back and checks:
  - the magic at both ends, Header first, Data End last in the data section, Footer last;
  - record lengths (every record ends where the next begins, nothing past the footer);
  - Data End's CRC32 (of every byte from the start of the file up to the Data End record;
    0 would mean "not available" and is rejected: lcmx always writes it);
  - the Footer: summary_start / summary_offset_start point at the sections that follow Data
    End, and summary_crc is the CRC32 from summary_start through the footer's
    summary_offset_start field;
  - Summary Offset records cover exactly their groups; summary Schema/Channel records repeat
    the data section's byte for byte; Statistics counts and times match the messages read;
  - schemas have ids > 0, encoding "jsonschema", valid JSON Schema data; channels reference a
    schema written before them, encoding "json"; messages reference a channel written before
    them; every message is valid JSON (UTF-8) and validates against its channel's schema
    (python3-jsonschema, Draft 2020-12; "number" also admits null, lcmx's NaN/infinity).
Prints per schema whether Foxglove's JSON Schema reader can use it:
  SCHEMA <name> foxglove=yes | foxglove=no: <why>        (tab-separated)
and one line per message, for the C++ test to compare field by field:
  MSG <topic> <schema name> <sequence> <log_time> <publish_time> <path>=<value> ... (tab-separated)
where <path> is dotted/indexed ("header.seq", "position[2]", "data[0]") and <value> is
json.dumps(ensure_ascii=False) of each leaf (so a string is quoted, NaN-as-null is null); then
  OK messages=N schemas=S channels=C
On the first violation: "FAIL <reason>" and exit status 1. Usage: mcap_check.py FILE
"""
import json
import struct
import sys
import zlib

MAGIC = b"\x89MCAP0\r\n"
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
STATISTICS, SUMMARY_OFFSET, DATA_END = 0x0B, 0x0E, 0x0F


class Bad(Exception):
    pass


class Cursor:
    def __init__(self, b):
        self.b, self.p = b, 0

    def take(self, n):
        if self.p + n > len(self.b):
            raise Bad("field runs past the end of its record")
        v = self.b[self.p:self.p + n]
        self.p += n
        return v

    def u8(self):
        return self.take(1)[0]

    def u16(self):
        return struct.unpack("<H", self.take(2))[0]

    def u32(self):
        return struct.unpack("<I", self.take(4))[0]

    def u64(self):
        return struct.unpack("<Q", self.take(8))[0]

    def string(self):
        return self.take(self.u32()).decode("utf-8")

    def blob32(self):
        return self.take(self.u32())

    def rest(self):
        return self.take(len(self.b) - self.p)


def flatten(v, path, out):
    if isinstance(v, dict):
        for k, x in v.items():
            flatten(x, f"{path}.{k}" if path else k, out)
    elif isinstance(v, list):
        for i, x in enumerate(v):
            flatten(x, f"{path}[{i}]", out)
    else:
        out.append(f"{path}={json.dumps(v, ensure_ascii=False)}")


def foxglove_problem(schema, where):
    """Foxglove's JSON Schema reader, as its documentation and source describe it: an object
    with "properties"; each property of type boolean, string, number, integer, object (the
    same rules), or array whose "items" are one of those but not an array; no "$ref", no type
    lists. Returns why a schema is outside that, or None."""
    if schema.get("type") != "object" or not isinstance(schema.get("properties"), dict):
        return f"{where} is not an object with properties"
    for name, prop in schema["properties"].items():
        here = f"{where}.{name}"
        t = prop.get("type")
        if t in ("boolean", "string", "number", "integer"):
            continue
        if t == "object":
            why = foxglove_problem(prop, here)
            if why:
                return why
        elif t == "array":
            it = prop.get("items", {}).get("type")
            if it == "object":
                why = foxglove_problem(prop["items"], here + "[]")
                if why:
                    return why
            elif it not in ("boolean", "string", "number", "integer"):
                return f"{here}: array of {json.dumps(prop.get('items'))[:60]}"
        else:
            return f"{here}: {json.dumps(prop)[:60]}"
    return None


def main(path):
    import jsonschema  # Debian: python3-jsonschema

    # JSON has no NaN nor infinity: lcmx writes them as null and its schemas say so in the
    # description of each float field, which stays "type": "number" (Foxglove's reader takes
    # no type lists). So "number" also admits null here, and nothing else is relaxed.
    base = jsonschema.Draft202012Validator
    checker = base.TYPE_CHECKER.redefine(
        "number", lambda c, x: x is None or base.TYPE_CHECKER.is_type(x, "number"))
    validator_class = jsonschema.validators.extend(base, type_checker=checker)

    data = open(path, "rb").read()
    if data[:8] != MAGIC:
        raise Bad("no leading magic")
    if data[-8:] != MAGIC:
        raise Bad("no trailing magic")
    records = []  # (offset, opcode, content)
    p = 8
    end = len(data) - 8
    while p < end:
        if p + 9 > end:
            raise Bad(f"record header at {p} runs into the trailing magic")
        op = data[p]
        (n,) = struct.unpack("<Q", data[p + 1:p + 9])
        if p + 9 + n > end:
            raise Bad(f"record 0x{op:02x} at {p} ({n} bytes) runs past the end")
        records.append((p, op, data[p + 9:p + 9 + n]))
        p += 9 + n
    if p != end:
        raise Bad("records do not end at the trailing magic")
    if not records or records[0][1] != HEADER:
        raise Bad("first record is not a Header")
    if records[-1][1] != FOOTER:
        raise Bad("last record is not a Footer")
    c = Cursor(records[0][2])
    c.string()  # profile
    c.string()  # library

    ends = [i for i, r in enumerate(records) if r[1] == DATA_END]
    if len(ends) != 1:
        raise Bad(f"{len(ends)} Data End records")
    de = ends[0]
    de_off = records[de][0]
    (crc,) = struct.unpack("<I", records[de][2][:4])
    if crc == 0:
        raise Bad("Data End has no CRC")
    if crc != zlib.crc32(data[:de_off]):
        raise Bad(f"Data End CRC {crc:08x} != {zlib.crc32(data[:de_off]):08x}")

    schemas, channels, raw_schema, raw_channel = {}, {}, {}, {}
    counts, times, out = {}, [], []
    validators = {}
    for off, op, body in records[1:de]:
        c = Cursor(body)
        if op == SCHEMA:
            sid, name, enc, sdata = c.u16(), c.string(), c.string(), c.blob32()
            if sid == 0:
                raise Bad("schema id 0")
            if enc != "jsonschema":
                raise Bad(f"schema {name}: encoding {enc!r}")
            if sid in schemas and raw_schema[sid] != body:
                raise Bad(f"schema id {sid} redefined differently")
            doc = json.loads(sdata.decode("utf-8"))
            jsonschema.Draft202012Validator.check_schema(doc)
            if doc.get("title") != name:
                raise Bad(f"schema {name}: title {doc.get('title')!r}")
            schemas[sid], raw_schema[sid] = (name, doc), body
            validators[sid] = validator_class(doc)
            why = foxglove_problem(doc, name)
            print(f"SCHEMA\t{name}\tfoxglove=" + ("yes" if why is None else "no: " + why))
        elif op == CHANNEL:
            cid, sid, topic, enc = c.u16(), c.u16(), c.string(), c.string()
            meta_bytes = Cursor(c.blob32())
            meta = {}
            while meta_bytes.p < len(meta_bytes.b):
                k = meta_bytes.string()
                meta[k] = meta_bytes.string()
            if sid not in schemas:
                raise Bad(f"channel {topic}: schema {sid} not written before it")
            if enc != "json":
                raise Bad(f"channel {topic}: message encoding {enc!r}")
            if meta.get("lcm_type") != schemas[sid][0]:
                raise Bad(f"channel {topic}: lcm_type {meta.get('lcm_type')!r}")
            if cid in channels and raw_channel[cid] != body:
                raise Bad(f"channel id {cid} redefined differently")
            channels[cid], raw_channel[cid] = (topic, sid), body
        elif op == MESSAGE:
            cid, seq, log_time, pub_time = c.u16(), c.u32(), c.u64(), c.u64()
            payload = c.rest()
            if cid not in channels:
                raise Bad(f"message at {off}: channel {cid} not written before it")
            topic, sid = channels[cid]
            msg = json.loads(payload.decode("utf-8"))
            errors = sorted(validators[sid].iter_errors(msg), key=lambda e: list(e.path))
            if errors:
                raise Bad(f"message at {off} on {topic}: does not match {schemas[sid][0]}: "
                          f"{list(errors[0].path)}: {errors[0].message}")
            counts[cid] = counts.get(cid, 0) + 1
            times.append(log_time)
            leaves = []
            flatten(msg, "", leaves)
            out.append("\t".join(["MSG", topic, schemas[sid][0], str(seq), str(log_time), str(pub_time)] + leaves))
        elif op in (HEADER, FOOTER, STATISTICS, SUMMARY_OFFSET):
            raise Bad(f"record 0x{op:02x} at {off} in the data section")
        # other opcodes (chunks, attachments, ...): lcmx writes none; a reader skips them

    # Footer and summary.
    foot_off, _, foot = records[-1]
    c = Cursor(foot)
    summary_start, summary_offset_start, summary_crc = c.u64(), c.u64(), c.u32()
    after_de = records[de + 1:-1]
    if summary_start == 0:
        if after_de:
            raise Bad("records after Data End but summary_start is 0")
    else:
        if not after_de or after_de[0][0] != summary_start:
            raise Bad(f"summary_start {summary_start} is not the record after Data End")
        want = zlib.crc32(data[summary_start:foot_off + 1 + 8 + 16])
        if summary_crc != want:
            raise Bad(f"summary CRC {summary_crc:08x} != {want:08x}")
        summary = [r for r in after_de if r[0] < (summary_offset_start or foot_off)]
        offsets = [r for r in after_de if summary_offset_start and r[0] >= summary_offset_start]
        if summary_offset_start and (not offsets or offsets[0][0] != summary_offset_start):
            raise Bad("summary_offset_start is not a record start")
        if any(op != SUMMARY_OFFSET for _, op, _ in offsets):
            raise Bad("a non Summary Offset record in the summary offset section")
        seen_ops = []
        stats = None
        for off, op, body in summary:
            if seen_ops and seen_ops[-1] != op and op in seen_ops:
                raise Bad(f"summary records not grouped by opcode (0x{op:02x})")
            seen_ops.append(op)
            if op == SCHEMA:
                sid = struct.unpack("<H", body[:2])[0]
                if raw_schema.get(sid) != body:
                    raise Bad(f"summary schema {sid} differs from the data section's")
            elif op == CHANNEL:
                cid = struct.unpack("<H", body[:2])[0]
                if raw_channel.get(cid) != body:
                    raise Bad(f"summary channel {cid} differs from the data section's")
            elif op == STATISTICS:
                if stats is not None:
                    raise Bad("two Statistics records")
                stats = body
        if set(raw_schema) != {struct.unpack("<H", b[:2])[0] for _, op, b in summary if op == SCHEMA}:
            raise Bad("summary lacks some schemas")
        if set(raw_channel) != {struct.unpack("<H", b[:2])[0] for _, op, b in summary if op == CHANNEL}:
            raise Bad("summary lacks some channels")
        for _, _, body in offsets:
            c = Cursor(body)
            gop, gstart, glen = c.u8(), c.u64(), c.u64()
            group = [r for r in summary if gstart <= r[0] < gstart + glen]
            if not group or group[0][0] != gstart or any(r[1] != gop for r in group):
                raise Bad(f"summary offset for 0x{gop:02x} does not match its group")
            last = group[-1]
            if last[0] + 9 + len(last[2]) != gstart + glen:
                raise Bad(f"summary offset for 0x{gop:02x}: wrong length")
            if gop not in seen_ops:
                raise Bad(f"summary offset for 0x{gop:02x}: no such group")
        if stats is not None:
            c = Cursor(stats)
            mcount, scount, ccount = c.u64(), c.u16(), c.u32()
            c.u32(), c.u32(), c.u32()  # attachments, metadata, chunks
            start, end_t = c.u64(), c.u64()
            per = Cursor(c.blob32())
            per_ch = {}
            while per.p < len(per.b):
                k = per.u16()
                per_ch[k] = per.u64()
            if mcount != sum(counts.values()) or scount != len(schemas) or ccount != len(channels):
                raise Bad(f"statistics {mcount}/{scount}/{ccount} != {sum(counts.values())}/{len(schemas)}/{len(channels)}")
            if times and (start != min(times) or end_t != max(times)):
                raise Bad("statistics start/end time wrong")
            if {k: v for k, v in per_ch.items() if v} != counts:
                raise Bad(f"statistics per channel {per_ch} != {counts}")
    for line in out:
        print(line)
    print(f"OK messages={sum(counts.values())} schemas={len(schemas)} channels={len(channels)}")


if __name__ == "__main__":
    try:
        main(sys.argv[1])
    except (Bad, ValueError, UnicodeDecodeError, KeyError, struct.error) as e:
        print(f"FAIL {e}")
        sys.exit(1)
    except Exception as e:  # jsonschema.SchemaError and the like
        print(f"FAIL {type(e).__name__}: {e}")
        sys.exit(1)
