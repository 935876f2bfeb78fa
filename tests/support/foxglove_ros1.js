// Reads deft_gym's binary (ROS 1) messages with Foxglove's own ROS 1 libraries - @foxglove/rosmsg
// parses the ros1msg schema text, @foxglove/rosmsg-serialization's MessageReader reads the bytes,
// as Foxglove does for a ros1 channel of an MCAP file - and compares every value with deft_gym's
// decoding (floats with Object.is: bit for bit, -0 and NaN included).
// Input (argv[2]): {"schemas": {name: text}, "messages": [{"schema", "data": base64 ROS 1 bytes,
// "ours": base64 JSON as deft_gym decodes it}]}. Prints one line; exits 1 when any message differs.
const fs = require("fs");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg-serialization");

const input = JSON.parse(fs.readFileSync(process.argv[2]));
const readers = {};
for (const [name, text] of Object.entries(input.schemas)) readers[name] = new MessageReader(parse(text));
let same = 0, numbers = 0;
const differ = [];

function compare(fox, ours, path) {
  if (typeof ours === "number") {
    numbers++;
    const x = Number(fox); // int64 fields come back as BigInt
    if (!(Object.is(x, ours) || (Number.isNaN(x) && Number.isNaN(ours)))) throw new Error(`${path}: ${fox} != ${ours}`);
  } else if (Array.isArray(ours)) {
    if (fox.length !== ours.length) throw new Error(`${path}: ${fox.length} items, not ${ours.length}`);
    ours.forEach((v, i) => compare(fox[i], v, `${path}[${i}]`));
  } else if (ours !== null && typeof ours === "object") {
    for (const k of Object.keys(ours)) compare(fox[k], ours[k], `${path}.${k}`);
  } else if (fox !== ours) {
    throw new Error(`${path}: ${fox} != ${ours}`);
  }
}

for (const m of input.messages) {
  const msg = readers[m.schema].readMessage(Buffer.from(m.data, "base64"));
  const rest = msg.json_rest; // the optional keys, JSON text (deft_gym merges them into the object)
  delete msg.json_rest;
  const fox = rest ? { ...msg, ...JSON.parse(rest) } : msg;
  try {
    compare(fox, JSON.parse(Buffer.from(m.ours, "base64").toString()), m.schema);
    same++;
  } catch (e) {
    differ.push(e.message);
  }
}
console.log(`${same} of ${input.messages.length} messages read by Foxglove's ROS 1 libraries equal deft_gym's (${numbers} numbers)` +
  (differ.length ? `; first difference: ${differ[0]}` : ""));
process.exit(differ.length ? 1 : 0);
