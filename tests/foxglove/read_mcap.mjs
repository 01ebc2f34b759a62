// Read an MCAP file the way Foxglove / Lichtblick do: @mcap/core's indexed reader (zstd
// chunks), each schema's FileDescriptorSet loaded with protobufjs, every message decoded.
import { McapIndexedReader } from "@mcap/core";
import { decompress as zstd } from "fzstd";
import protobufjs from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import { open } from "node:fs/promises";

const path = process.argv[2];
const fh = await open(path, "r");
const size = (await fh.stat()).size;
const readable = {
  size: async () => BigInt(size),
  read: async (offset, length) => {
    const buf = new Uint8Array(Number(length));
    await fh.read(buf, 0, Number(length), Number(offset));
    return buf;
  },
};
const reader = await McapIndexedReader.Initialize({
  readable,
  decompressHandlers: { zstd: (data, size) => zstd(data, new Uint8Array(Number(size))) },
});
const types = new Map();
for (const [id, schema] of reader.schemasById) {
  if (schema.encoding !== "protobuf") throw new Error(`schema ${schema.name}: ${schema.encoding}`);
  const set = descriptor.FileDescriptorSet.decode(schema.data);
  const root = protobufjs.Root.fromDescriptor(set);
  types.set(id, root.lookupType(schema.name));
}
const counts = {};
for await (const msg of reader.readMessages()) {
  const channel = reader.channelsById.get(msg.channelId);
  const type = types.get(channel.schemaId);
  const obj = type.toObject(type.decode(msg.data));
  const key = `${channel.topic} ${type.fullName.replace(/^\./, "")}`;
  counts[key] = (counts[key] ?? 0) + 1;
  if (type.fullName === ".foxglove.CompressedImage" && !(obj.format === "png" && obj.data.length > 8))
    throw new Error(`bad image on ${channel.topic}`);
}
console.log(JSON.stringify({ messages: Number(reader.statistics.messageCount), counts }, null, 1));
