// A Sparkplug B host's view of the gateway, with Eclipse Tahu's JavaScript library
// (sparkplug-payload, on protobufjs): nothing here shares code with the gateway.
//
//   node host.js decode   lines "TOPIC HEX" in (mosquitto_sub -F '%t %x'), one JSON line out
//                         per message: {"topic", "payload": Tahu's decodePayload, "raw": the
//                         protobuf fields as protobufjs reads them}; 64-bit values as text
//   node host.js encode   one JSON payload in (Tahu's object form), its bytes out as hex
"use strict";

const readline = require("readline");
const Long = require("long");
const sparkplug = require("sparkplug-payload").get("spBv1.0");
const proto = require("sparkplug-payload/lib/sparkplugPayloadProto");

const Payload = proto.org.eclipse.tahu.protobuf.Payload;

function plain(key, value) {
  if (Long.isLong(value)) {
    return value.toString();
  }
  if (value instanceof Uint8Array) {
    return Buffer.from(value).toString("hex");
  }
  return value;
}

function decode() {
  const lines = readline.createInterface({ input: process.stdin });
  lines.on("line", (line) => {
    const [topic, hex] = line.trim().split(" ");
    if (!topic) {
      return;
    }
    const out = { topic };
    if (topic.startsWith("spBv1.0/STATE/")) {
      out.state = Buffer.from(hex || "", "hex").toString("utf8");
    } else {
      const bytes = Buffer.from(hex || "", "hex");
      try {
        out.payload = sparkplug.decodePayload(bytes);
        out.raw = Payload.toObject(Payload.decode(bytes), { longs: String, defaults: false });
      } catch (error) {
        out.error = String(error);
      }
    }
    process.stdout.write(JSON.stringify(out, plain) + "\n");
  });
}

function encode() {
  let text = "";
  process.stdin.on("data", (chunk) => {
    text += chunk;
  });
  process.stdin.on("end", () => {
    const bytes = sparkplug.encodePayload(JSON.parse(text));
    process.stdout.write(Buffer.from(bytes).toString("hex") + "\n");
  });
}

if (process.argv[2] === "decode") {
  decode();
} else if (process.argv[2] === "encode") {
  encode();
} else {
  process.stderr.write("usage: node host.js decode|encode\n");
  process.exit(2);
}
