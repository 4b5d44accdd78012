// Decodes the arena's golden wire vectors with @msgpack/msgpack, an implementation independent of the
// Python encoder, and prints {vector name: decoded value} as JSON on stdout.
//
// JSON cannot carry every msgpack value exactly, so a few values are printed as tagged objects:
//   64-bit integers (decoded as BigInt)  -> {"$int": "<decimal digits>"}
//   NaN, +/-Infinity and negative zero   -> {"$float": "nan" | "inf" | "-inf" | "-0"}
//   binary                               -> {"$bin": "<hex>"}
// Every other number is printed by JSON.stringify, whose shortest round-trip form parses back to the
// very same float64.
//
// Usage: node decode.mjs [directory of vectors]   (default: ../golden beside this script)

import { readdirSync, readFileSync } from "node:fs";
import { dirname, join, resolve } from "node:path";
import { fileURLToPath } from "node:url";
import { decode } from "@msgpack/msgpack";

const here = dirname(fileURLToPath(import.meta.url));
const dir = resolve(process.argv[2] ?? join(here, "..", "golden"));

function tag(value) {
  if (typeof value === "bigint") return { $int: value.toString() };
  if (typeof value === "number") {
    if (Number.isNaN(value)) return { $float: "nan" };
    if (value === Infinity) return { $float: "inf" };
    if (value === -Infinity) return { $float: "-inf" };
    if (Object.is(value, -0)) return { $float: "-0" };
    return value;
  }
  if (value instanceof Uint8Array) return { $bin: Buffer.from(value).toString("hex") };
  if (Array.isArray(value)) return value.map(tag);
  if (value !== null && typeof value === "object") {
    const out = {};
    for (const [k, v] of Object.entries(value)) out[k] = tag(v);
    return out;
  }
  return value; // string, boolean, null
}

function hexBytes(hex, file) {
  if (typeof hex !== "string" || hex.length % 2 !== 0 || !/^[0-9a-f]*$/.test(hex)) {
    throw new Error(`${file}: "hex" is not an even-length lower-case hex string`);
  }
  return Buffer.from(hex, "hex");
}

const out = {};
for (const file of readdirSync(dir).filter((f) => f.endsWith(".json")).sort()) {
  // Only "name" and "hex" are read: JSON.parse would round the big integers of the "json" field.
  const vector = JSON.parse(readFileSync(join(dir, file), "utf8"));
  out[vector.name] = tag(decode(hexBytes(vector.hex, file), { useBigInt64: true }));
}
process.stdout.write(JSON.stringify(out, null, 1) + "\n");
